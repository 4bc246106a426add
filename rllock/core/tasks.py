"""Many tasks for one network (`rllock train --tasks SPEC`): task groups, random shapes, and the draws.

SPEC lists task groups separated by commas, each `SHAPE:K` or `SHAPE:KLO-KHI`, optionally `@C`:
  cube4:6-9,cube5:12-16,cube6:18-25,box:6x5x4:8-12,random:60-200:6-20,random:300-1000:15-80@16
SHAPE is anything `--shape` takes (a built-in name, `box:WxHxD`, a file), or `random:NLO-NHI`: a fresh
connected shape of NLO..NHI voxels for every draw, grown inside the group's canvas (training diversity).
Each self-play batch draws a group uniformly, then a shape of the group and a K of its range uniformly
(for random shapes, K is kept to at most N/2, so that a piece has at least 2 voxels).

Canvases: a group is played on the run's canvas (--canvas, or an --init checkpoint's; else 8, or the
smallest multiple of 4 that fits every listed shape), or on its own canvas C where it says `@C`. So one
run can train one network on several canvases (the U-Net's weights do not depend on the side); each
state is stored on the largest and learned from on its own (`rllock.search.canvas.crop_canvas`), and a
checkpoint plays a shape on the smallest canvas that fits it, as it was trained.
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass

import numpy as np

from rllock.core.env import Task, make_task
from rllock.core.shapes import crop, grid_sha256, load_shape
from rllock.core.verifier import CHECKER_VERSION
from rllock.errors import RLLockError

DEFAULT_CANVAS = 8  # the paper's canvas; random shapes are grown to fit it
NEIGHBOURS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])


@dataclass(frozen=True, eq=False)
class TaskGroup:
    spec: str  # the group as written, e.g. "cube4:6-9"
    grid: np.ndarray | None  # the shape; None: a random shape per draw
    sizes: tuple[int, int] | None  # random shapes: voxel counts, inclusive
    pieces: tuple[int, int]  # K range, inclusive
    canvas: int = 0  # the side of the canvas it is played on (`parse_tasks` sets it)

    def max_piece_size(self) -> int:
        """The largest n = floor(N / K) a draw of this group can have."""
        if self.grid is not None:
            return int(self.grid.sum()) // self.pieces[0]
        assert self.sizes is not None
        return max(self.sizes[1] // self.pieces[0], 2)  # K cut to N/2 on small shapes: n = 2


@dataclass(frozen=True, eq=False)
class TaskSet:
    """Task groups, each on its canvas; plain data (numpy grids), so that it travels to actor processes."""

    spec: str
    groups: tuple[TaskGroup, ...]
    removal: str

    @property
    def canvas(self) -> int:
        """The smallest canvas of the run: a checkpoint's own, on which it plays every shape that fits."""
        return min(group.canvas for group in self.groups)

    @property
    def store_canvas(self) -> int:
        """The largest canvas of the run, on which the replay buffer stores every state."""
        return max(group.canvas for group in self.groups)

    def canvases(self) -> tuple[int, ...]:
        return tuple(sorted({group.canvas for group in self.groups}))

    def draw(self, rng: np.random.Generator) -> tuple[int, Task]:
        """(group number, a task of it), as the module docstring says."""
        g = int(rng.integers(len(self.groups)))
        return g, self._task(self.groups[g], rng)

    def _task(self, group: TaskGroup, rng: np.random.Generator, middle: bool = False) -> Task:
        lo, hi = group.pieces
        if group.grid is not None:
            k = (lo + hi) // 2 if middle else int(rng.integers(lo, hi + 1))
            return make_task(group.grid, k, self.removal, name=group.spec.rsplit(":", 1)[0])
        size_lo, size_hi = group.sizes or (0, 0)
        size = (size_lo + size_hi) // 2 if middle else int(rng.integers(size_lo, size_hi + 1))
        hi = min(hi, size // 2)
        k = max(2, (lo + hi) // 2 if middle else int(rng.integers(min(lo, hi), hi + 1)))
        grid = random_shape(rng, size, group.canvas)
        return make_task(grid, k, self.removal, name=f"random{size}")

    def validation_tasks(self, seed: int) -> list[Task]:
        """One fixed task per group, the same at every validation: the middle K of its range (a random
        group: a shape of its middle size, drawn from `seed`)."""
        return [
            self._task(group, np.random.default_rng([seed, g]), middle=True)
            for g, group in enumerate(self.groups)
        ]

    def max_piece_size(self) -> int:
        return max(group.max_piece_size() for group in self.groups)

    def identity(self) -> dict:
        """What a multi-task checkpoint is for (stored where a single-task one stores its task)."""
        return {
            "tasks": self.spec,
            "groups": [group.spec for group in self.groups],
            "shapes_sha256": [None if g.grid is None else grid_sha256(g.grid) for g in self.groups],
            "removal": self.removal,
            "canvas": self.canvas,
            "canvases": list(self.canvases()),
            "checker_version": CHECKER_VERSION,
        }


def _range(text: str, what: str, item: str) -> tuple[int, int]:
    match = re.fullmatch(r"(\d+)(?:-(\d+))?", text)
    if not match:
        raise RLLockError(f"bad {what} {text!r} in task group {item!r}: use N or LO-HI")
    lo = int(match.group(1))
    hi = int(match.group(2) or lo)
    if hi < lo:
        raise RLLockError(f"bad {what} {text!r} in task group {item!r}: {hi} < {lo}")
    return lo, hi


def parse_tasks(spec: str, *, canvas: int | None = None, removal: str = "straight", step: int = 4) -> TaskSet:
    """The task set named by `spec` (module docstring): groups without `@C` on `canvas` (default: 8, or
    the smallest multiple of `step` that fits every such shape when one is larger), with clear errors
    for what cannot be trained."""
    items = [item.strip() for item in spec.split(",") if item.strip()]
    if not items:
        raise RLLockError("--tasks is empty: list groups like cube4:6-9,random:60-200:6-20")
    parsed = [(_group(item), _own_canvas(item, step)) for item in items]
    fixed = [max(g.grid.shape) for g, own in parsed if g.grid is not None and own is None]
    side = canvas or -(-max([DEFAULT_CANVAS, *fixed]) // step) * step
    groups = tuple(dataclasses.replace(group, canvas=own or side) for group, own in parsed)
    for group in groups:
        if group.grid is not None and max(group.grid.shape) > group.canvas:
            raise RLLockError(
                f"task group {group.spec!r}: the shape does not fit the {group.canvas}^3 canvas"
            )
        if group.sizes is not None and group.sizes[1] > group.canvas**3:
            raise RLLockError(
                f"task group {group.spec!r}: {group.sizes[1]} voxels exceed the {group.canvas}^3 canvas"
            )
    return TaskSet(spec, groups, removal)


def _own_canvas(item: str, step: int) -> int | None:
    """The canvas a group asks for with `@C`, or None."""
    if "@" not in item:
        return None
    text = item.rsplit("@", 1)[1]
    if not text.isdigit() or int(text) < step or int(text) % step:
        raise RLLockError(f"bad canvas {text!r} in task group {item!r}: use @C, C a multiple of {step}")
    return int(text)


def _group(item: str) -> TaskGroup:
    """One task group as written (without its canvas)."""
    body = item.rsplit("@", 1)[0]
    if ":" not in body:
        raise RLLockError(f"task group {item!r} has no piece count: use SHAPE:K or SHAPE:KLO-KHI")
    shape, k_text = body.rsplit(":", 1)
    pieces = _range(k_text, "piece count", item)
    if pieces[0] < 2:
        raise RLLockError(f"task group {item!r}: K must be at least 2")
    if pieces[1] > np.iinfo(np.int8).max:
        raise RLLockError(f"task group {item!r}: K at most {np.iinfo(np.int8).max} in multi-task runs")
    if shape.startswith("random:"):
        sizes = _range(shape.removeprefix("random:"), "voxel count", item)
        if sizes[0] < 4:
            raise RLLockError(f"task group {item!r}: random shapes need at least 4 voxels")
        return TaskGroup(item, None, sizes, pieces)
    grid = load_shape(shape)
    if pieces[1] > grid.sum():
        raise RLLockError(f"task group {item!r}: K = {pieces[1]} exceeds the shape's {grid.sum()} voxels")
    return TaskGroup(item, grid, None, pieces)


def random_shape(rng: np.random.Generator, size: int, canvas: int) -> np.ndarray:
    """A connected shape of `size` voxels inside the canvas, cropped to its bounding box. It grows one
    voxel at a time from the canvas centre; a free neighbour is chosen with weight (its filled
    neighbours)^3, so shapes come out as compact solids with some bumps, not as thin branching trees
    (which no interlocking assembly of several voxels per piece could fill)."""
    if size > canvas**3:
        raise RLLockError(f"a random shape of {size} voxels does not fit the {canvas}^3 canvas")
    grid = np.zeros((canvas,) * 3, bool)
    grid[(canvas // 2,) * 3] = True
    for _ in range(size - 1):
        filled = np.argwhere(grid)
        around = (filled[:, None, :] + NEIGHBOURS[None]).reshape(-1, 3)
        inside = ((around >= 0) & (around < canvas)).all(axis=1)
        around = np.unique(around[inside], axis=0)
        around = around[~grid[tuple(around.T)]]
        padded = np.pad(grid, 1)
        touching = sum(padded[tuple((around + 1 + d).T)].astype(np.int64) for d in NEIGHBOURS)
        weights = touching.astype(np.float64) ** 3
        pick = around[rng.choice(len(around), p=weights / weights.sum())]
        grid[tuple(pick)] = True
    return crop(grid)
