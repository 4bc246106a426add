"""The guide network's curriculum (`rllock train-guide`): a task per search, drawn from random compact
shapes and shipped shapes, with K from 5 to `max_pieces` and both removal modes; or, with `--cells`,
drawn from the tasks named there (a guide taught the one task a user cannot solve), each at its K or,
with `--edge`, at a K that moves with its searches' outcomes (`edge_pieces`).

Pieces have 4 to 40 voxels (n drawn log-uniformly, so that small pieces, where searches fail, are as
common as large ones), and K = N // n within [5, max_pieces]. mario and spider, the shapes the
benchmarks find hardest, are left out, so that what the guide does there is
zero-shot; so are their meshes.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np

from rllock.config import GuideTrainConfig
from rllock.core.env import Task, make_task, tight
from rllock.core.feasibility import check_feasible, impossibility
from rllock.core.shapes import crop, load_shape
from rllock.errors import RLLockError

SHAPES = ("cube4", "cube5", "cube6", "ring", "stairs", "tube", "sofa", "bunny", "shelf", "cubeweird",
          "desia-bunny", "desia-dog", "box:10x8x6", "box:12x12x3")  # fmt: skip
PATH_SHARE = 0.3  # of the tasks use DESIA's path removal


@dataclass(frozen=True)
class NamedTask:
    """A task as `rllock bench guide --cells` and `train-guide --cells` write it: SHAPE:K or SHAPE:K:path,
    SHAPE a shape name, a .puz/.vol/.npy file, or a mesh with @RESOLUTION (bunny.stl@24:40)."""

    label: str
    shape: str
    pieces: int
    removal: str
    resolution: int | None

    def task(self) -> Task:
        return make_task(self.shape, self.pieces, self.removal, resolution=self.resolution, name=self.label)


def parse_named_task(item: str) -> NamedTask:
    parts = item.split(":")
    removal = "straight"
    if parts[-1] in ("path", "straight"):
        removal = parts.pop()
    if len(parts) < 2 or not parts[-1].isdigit():
        raise RLLockError(f"bad cell {item!r}: use SHAPE:K or SHAPE:K:path (a mesh as FILE@RESOLUTION:K)")
    shape, pieces = ":".join(parts[:-1]), int(parts[-1])
    resolution = None
    if "@" in shape:
        shape, _, res = shape.rpartition("@")
        if not res.isdigit():
            raise RLLockError(f"bad resolution in cell {item!r}: use FILE@RESOLUTION:K")
        resolution = int(res)
    return NamedTask(item, shape, pieces, removal, resolution)


def named_tasks(spec: str) -> list[Task]:
    """The tasks of `--cells` (comma-separated `NamedTask`s), each checked: a clear error for a shape
    that cannot be loaded or a task that has no assembly."""
    tasks = [parse_named_task(item.strip()).task() for item in spec.split(",") if item.strip()]
    if not tasks:
        raise RLLockError("--cells is empty: give tasks like mario:60,desia-bunny:80:path")
    for task in tasks:
        check_feasible(task)
    return tasks


def edge_pieces(pieces: int, solved: bool, task: Task) -> int:
    """`--edge`: the K of `task`'s cell (given as `task.pieces`) for its next search, after a search at K =
    `pieces` that `solved` or not: the next K up after a solve, down after a failure, at which the last
    piece is under twice the others (`tight`: the hardest K of the next piece size, smaller or larger);
    within [K/2, N/4] (pieces of at least 4 voxels, unless the cell asked for smaller ones), passing over a
    K a proof rules out (spider: K = 20-42); K stays when there is none (the beetle at resolution 24
    above K = 66: its two antenna tips)."""
    low, high = max(2, task.pieces // 2), max(task.pieces, task.size // 4)
    step = 1 if solved else -1
    moved = pieces + step
    while low <= moved <= high:
        if tight(task.size, moved) and impossibility(replace(task, pieces=moved)) is None:
            return moved
        moved += step
    return pieces


def draw_task(
    rng: np.random.Generator,
    config: GuideTrainConfig,
    named: list[Task] | None = None,
    pieces: Mapping[str, int] | None = None,
) -> Task:
    """A feasible task of the curriculum (module docstring): one of `named` when there are any, at the K
    that `pieces` gives for its cell (`edge_pieces`; by its label), if any."""
    if named:
        task = named[int(rng.integers(len(named)))]
        if pieces and task.shape_name in pieces:
            return replace(task, pieces=pieces[task.shape_name])
        return task
    while True:
        if rng.random() < 0.5:
            name = str(SHAPES[rng.integers(len(SHAPES))])
            grid, label = load_shape(name), name
        else:
            size = int(np.exp(rng.uniform(np.log(config.min_voxels), np.log(config.max_voxels))))
            grid, label = blob(rng, size), f"random{size}"
        voxels = int(grid.sum())
        n = int(np.exp(rng.uniform(np.log(4), np.log(40))))
        k = int(np.clip(voxels // n, 5, config.max_pieces))
        if k > voxels // 2:
            continue
        removal = "path" if rng.random() < PATH_SHARE else "straight"
        task = make_task(grid, k, removal, name=label)
        if impossibility(task) is None:
            return task


def blob(rng: np.random.Generator, size: int) -> np.ndarray:
    """A connected compact shape of `size` voxels, cropped: grown one voxel at a time from a centre, a
    free neighbour chosen with weight (its filled neighbours)^3, as `rllock.core.tasks.random_shape`
    grows them, with the weights kept up to date instead of recomputed (linear in the canvas, not in
    the shape, per voxel)."""
    side = int(np.ceil(2.0 * size ** (1 / 3))) + 2
    filled = np.zeros((side,) * 3, bool)
    touching = np.zeros((side,) * 3, np.int64)
    _fill(filled, touching, (side // 2,) * 3)
    for _ in range(size - 1):
        cumulative = np.cumsum(np.where(filled, 0, touching).ravel() ** 3)
        flat = int(np.searchsorted(cumulative, rng.random() * cumulative[-1], side="right"))
        pick = np.unravel_index(flat, filled.shape)
        _fill(filled, touching, pick)
    return crop(filled)


def _fill(filled: np.ndarray, touching: np.ndarray, at: tuple) -> None:
    filled[at] = True
    for axis in range(3):
        for step in (-1, 1):
            there = list(at)
            there[axis] += step
            if 0 < there[axis] < filled.shape[axis] - 1:  # the border stays empty: the shape fits
                touching[tuple(there)] += 1
