"""A single-task checkpoint's task identity: what it was made for, stored in its metadata, and read back
as a task. (A multi-task run's identity is `rllock.core.tasks.TaskSet.identity`.)"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rllock.core.env import Task, make_task
from rllock.core.shapes import from_xfastest, grid_sha256, to_xfastest
from rllock.core.verifier import CHECKER_VERSION
from rllock.errors import RLLockError


def task_identity(task: Task, canvas: int) -> dict:
    """What a checkpoint is for: loading it for anything else is an error."""
    grid = task.topology.grid
    return {
        "shape": task.shape_name,
        "dimensions": list(grid.shape),
        "grid": [int(v) for v in to_xfastest(grid.astype(np.int8))],
        "grid_sha256": grid_sha256(grid),
        "pieces": task.pieces,
        "removal": task.removal,
        "canvas": canvas,
        "checker_version": CHECKER_VERSION,
    }


def task_from_identity(identity: dict) -> Task:
    grid = from_xfastest(np.asarray(identity["grid"]), tuple(identity["dimensions"])) != 0
    return make_task(grid, int(identity["pieces"]), identity["removal"], name=identity["shape"])


def describe_identity(identity: dict) -> str:
    """A task identity (`task_identity`, or a multi-task run's) in words."""
    if "tasks" in identity:
        return f"tasks {identity['tasks']}, removal {identity.get('removal')}"
    dims = "x".join(str(d) for d in identity["dimensions"])
    return f"{identity['shape']} ({dims}) K={identity['pieces']}, removal {identity['removal']}"


def check_same_task(saved: dict, wanted: dict, where: Path) -> None:
    """Refuse a checkpoint made for another task than `wanted`, saying both in words."""
    keys = ("tasks", "grid_sha256", "pieces", "removal", "canvas", "checker_version")
    differs = [key for key in keys if saved.get(key) != wanted.get(key)]
    if not differs:
        return
    there, here = describe_identity(saved), describe_identity(wanted)
    if "canvas" in differs:
        there, here = (
            f"{there}, on a {saved.get('canvas')}^3 canvas",
            f"{here}, on a {wanted.get('canvas')}^3 canvas",
        )
    if "checker_version" in differs:
        there = f"{there}, checkers version {saved.get('checker_version')}"
        here = f"{here}, checkers version {wanted.get('checker_version')}"
    if there == here:  # only the grid differs: two shapes of the same name and size
        here = f"{here}, but another shape of that name and size"
    raise RLLockError(f"checkpoint {where} was made for another task: {there}; this task is {here}")
