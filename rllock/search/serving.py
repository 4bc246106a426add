"""Which task a checkpoint serves, and on which canvas: the one place that decides it.

A single-task checkpoint plays its own task; a task the user names is a check of it (the same shape, K,
removal mode, canvas and checkers, or a one-line error saying both tasks in words). A multi-task
checkpoint plays the task the user names, on the smallest canvas it was trained on where the shape
fits, else on a larger one up to `MAX_CANVAS` (the U-Net is convolutional and its value reads a mean
over the canvas, so its weights do not depend on the side).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from rllock.core.env import Task, make_task
from rllock.core.identity import check_same_task, task_from_identity, task_identity
from rllock.core.verifier import CHECKER_VERSION
from rllock.errors import RLLockError
from rllock.files.checkpoint import Metadata
from rllock.search.network import fit_canvas

MAX_CANVAS = 16
"""The largest canvas a multi-task checkpoint plays on beyond its own: the U-Net's cost per evaluation
grows with the canvas's C^3 voxels."""


@dataclass(frozen=True)
class Named:
    """A task as a user names it for a checkpoint (`--shape`, `--pieces`, `--removal`, `--resolution`),
    every part optional; an unnamed removal mode is the checkpoint's own. --removal alone names the
    checkpoint's own shape and K with that removal mode."""

    shape: str | None = None
    pieces: int | None = None
    removal: str | None = None
    resolution: int | None = None

    def task(self, meta: Metadata) -> Task | None:
        """The named task (None when no shape is named)."""
        if self.shape is None and self.pieces is None:
            return None
        if self.shape is None or self.pieces is None:
            raise RLLockError("give both --shape and --pieces to check the checkpoint's task, or neither")
        return make_task(self.shape, self.pieces, self.removal or meta.removal, resolution=self.resolution)

    def identity(self, meta: Metadata) -> dict | None:
        """The identity of the named task on a single-task checkpoint's canvas, to compare with its own."""
        task = self.task(meta)
        if task is not None:
            return task_identity(task, meta.canvas)
        return None if self.removal is None else {**meta.task, "removal": self.removal}


Wanted = Task | Named | None
"""What a caller asks a checkpoint for: a task, a task as named on the command line, or nothing (a
single-task checkpoint's own)."""


def served(meta: Metadata, where: Path, wanted: Wanted = None) -> tuple[Task, int]:
    """(the task the checkpoint at `where` plays for `wanted`, the canvas side it plays it on)."""
    if meta.multitask:
        task = wanted.task(meta) if isinstance(wanted, Named) else wanted
        if task is None:
            raise RLLockError(
                f"checkpoint {where} serves many tasks ({meta.task['tasks']}): name one with --shape and "
                "--pieces"
            )
        return task, canvas_for(task, meta, where)
    expect = task_identity(wanted, meta.canvas) if isinstance(wanted, Task) else None
    if isinstance(wanted, Named):
        expect = wanted.identity(meta)
    if expect is not None:
        check_same_task(meta.task, expect, where)
    return task_from_identity(meta.task), meta.canvas


def canvas_for(task: Task, meta: Metadata, where: Path) -> int:
    """The canvas on which a multi-task checkpoint plays `task`, a task it can serve (its removal mode and
    checkers): the smallest canvas it was trained on where the shape fits, else the smallest larger one
    that does, up to MAX_CANVAS."""
    for key, here in (("removal", task.removal), ("checker_version", CHECKER_VERSION)):
        if meta.task.get(key) != here:
            raise RLLockError(f"checkpoint {where} was made for {key} {meta.task.get(key)!r}, not {here!r}")
    fits = [c for c in meta.canvases if max(task.topology.dims) <= c]
    if fits:
        return min(fits)
    canvas = fit_canvas(task, dataclasses.replace(meta.config.net, canvas=None)).canvas_side()
    if canvas > MAX_CANVAS:
        raise RLLockError(
            f"shape {task.shape_name} {task.topology.dims} does not fit the largest canvas checkpoint "
            f"{where} plays on ({MAX_CANVAS}^3)"
        )
    return canvas


def serves(meta: Metadata, where: Path, wanted: Wanted) -> bool:
    """Whether the checkpoint can play `wanted` (what `served` checks, without the error)."""
    try:
        served(meta, where, wanted)
    except RLLockError:
        return False
    return True


def checkpoint_for(task: Task) -> str:
    """The shipped checkpoint that generates for `task`: one trained for exactly this task, else the
    multi-task `general` where it plays the task; a one-line error when none does."""
    from rllock.files.checkpoint import SHIPPED, read_metadata, shipped_names

    names = shipped_names()
    # A checkpoint trained for the task itself before the one trained for many.
    for name in sorted(names, key=lambda n: n == "general"):
        if serves(read_metadata(SHIPPED / name), SHIPPED / name, task):
            return name
    raise RLLockError(
        f"no shipped checkpoint generates {task.shape_name} K={task.pieces} (removal={task.removal}): "
        "use the search solver"
    )
