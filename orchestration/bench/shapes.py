"""`rllock bench shapes`: large shapes swept over K, the time to the first valid assembly.

For each shape (DESIA's bunny and dog, the high-level mario, bunny and spider, and a mesh at the
resolutions asked for) and each K of the sweep that the shape allows, each arm runs until its first
valid assembly or the time limit: the search solver (with `--workers 1,2`: one search, and two at once,
`rllock.search.portfolio`), and `general` zero-shot (on a canvas larger than
its own where the shape needs one: `rllock.search.serving.canvas_for`). A task with a proof that it
has no assembly (`rllock.core.feasibility`) is marked so without searching. Times are wall clock from
the start of the arm, `general`'s loading and compiling included.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass

import numpy as np

from rllock.core.env import Task, make_task
from rllock.core.feasibility import impossibility
from rllock.core.shapes import load_shape
from rllock.core.verifier import verify_labels
from rllock.errors import RLLockError
from rllock.orchestration.bench.arms import policy_arm, warm_process
from rllock.search.dfs import SearchStats
from rllock.search.guide import Guide
from rllock.search.inference import load_policy, with_simulations
from rllock.search.portfolio import portfolio_search
from rllock.search.search_config import SearchConfig
from rllock.search.solver import search

log = logging.getLogger(__name__)

SHAPES = ("desia-bunny", "desia-dog", "mario", "bunny", "spider")
PIECES = tuple(range(10, 101, 10))


@dataclass(frozen=True)
class Cell:
    """One arm on one task: seconds to the first valid assembly, or None within `limit`."""

    seconds: float | None
    limit: float
    placed: int | None = None  # the solver's best: pieces placed in its deepest state
    impossible: str | None = None  # the reason a task provably has no assembly

    def text(self, pieces: int) -> str:
        if self.impossible:
            return "impossible"
        if self.seconds is not None:
            return f"{self.seconds:.1f}"
        best = f" (best {self.placed}/{pieces - 1})" if self.placed is not None else ""
        return f"none in {self.limit:.0f}{best}"


@dataclass(frozen=True)
class ShapeTask:
    shape: str  # a shape name or a mesh path
    label: str  # the shape's name in the table
    resolution: int | None = None

    def load(self) -> np.ndarray:
        """The shape's voxels, loaded (a mesh voxelized) once for its whole sweep; a bad shape is an
        error here."""
        return load_shape(self.shape, self.resolution)


def shape_tasks(shapes: list[str], mesh: str | None, resolutions: list[int]) -> list[ShapeTask]:
    """The named shapes, then the mesh at each resolution."""
    out = [ShapeTask(s, s) for s in shapes]
    if mesh:
        out += [ShapeTask(mesh, f"mesh@{r}", r) for r in resolutions]
    return out


def solver_cell(
    task: Task,
    time_limit: float,
    seed: int,
    guide: Guide | None = None,
    workers: int = 1,
    threads: int = 1,
    config: SearchConfig = SearchConfig(),
) -> Cell:
    """Seconds to the search's first valid assembly (verified), with `guide` when given, by `workers`
    searches at once (`rllock.search.portfolio`; their start-up counted) or one on `threads` threads."""
    stats = SearchStats()
    start = time.perf_counter()
    if threads > 1 and workers > 1:
        raise ValueError("a portfolio shares its cores between seeds and threads itself")
    if workers == 1:
        searches = search(
            task, seed=seed, time_limit=time_limit, stats=stats, guide=guide, threads=threads, config=config
        )
    else:
        searches = portfolio_search(
            task, seed=seed, workers=workers, time_limit=time_limit, stats=stats, guide=guide, config=config
        )
    for found in searches:
        seconds = time.perf_counter() - start
        if not verify_labels(found.labels, task.removal).valid:
            raise AssertionError(f"the search returned an assembly of {task.shape_name} the verifier rejects")
        searches.close()  # the portfolio's workers stop now
        return Cell(seconds, time_limit)
    return Cell(None, time_limit, placed=stats.placed)


def general_cell(task: Task, time_limit: float, seed: int, batch: int, simulations: int | None) -> Cell:
    def load():
        return with_simulations(load_policy("general", task), simulations)

    try:
        arm, _ = policy_arm(load, count=1, batch=batch, time_limit=time_limit, seed=seed)
    except RLLockError as exc:  # e.g. a shape beyond the largest canvas general plays on
        log.warning("general on %s K=%d: %s", task.shape_name, task.pieces, exc)
        return Cell(None, time_limit)
    return Cell(arm.seconds if arm.valid else None, time_limit)


def solver_arm(workers: int, threads: int = 1) -> str:
    """The solver arm's name with `workers` searches at once or one on `threads` sampling threads:
    "solver", "solver x2", "solver t2", ..."""
    return "solver" + (f" x{workers}" if workers > 1 else "") + (f" t{threads}" if threads > 1 else "")


def solver_layout(arm: str) -> tuple[int, int]:
    """(workers, threads) of a solver arm's name."""
    marks = {word[0]: int(word[1:]) for word in arm.split()[1:]}
    return marks.get("x", 1), marks.get("t", 1)


@dataclass(frozen=True)
class Row:
    shape: str
    voxels: int
    dims: tuple[int, ...]
    pieces: int
    removal: str
    cells: dict[str, Cell]


def bench_shapes(
    tasks: list[ShapeTask],
    pieces: list[int],
    *,
    removals: list[str],
    arms: list[str],
    time_limit: float,
    seed: int,
    batch: int,
    simulations: int | None = None,
) -> list[Row]:
    """One row per shape, removal mode and K that the shape allows; `simulations` per decision for
    `general` (None: as it was trained)."""
    warm_process("cube4", 4)  # numba's cache and JAX's backend, once, before any arm is timed
    rows = []
    for shape in tasks:
        grid = shape.load()
        voxels = int(grid.sum())
        for removal in removals:
            for k in pieces:
                if k > voxels:
                    log.info("%s K=%d: skipped, K is over the shape's %d voxels", shape.label, k, voxels)
                    continue
                task = make_task(grid, k, removal, name=shape.label)
                reason = impossibility(task)
                cells = {}
                for arm in arms:
                    if reason is not None:
                        cells[arm] = Cell(None, time_limit, impossible=reason)
                    elif arm.startswith("solver"):
                        workers, threads = solver_layout(arm)
                        cells[arm] = solver_cell(task, time_limit, seed, workers=workers, threads=threads)
                    else:
                        cells[arm] = general_cell(task, time_limit, seed, batch, simulations)
                row = Row(shape.label, task.size, task.topology.dims, k, removal, cells)
                log.info(
                    "%s K=%d %s: %s",
                    shape.label,
                    k,
                    removal,
                    ", ".join(f"{a} {c.text(k)}" for a, c in cells.items()),
                )
                rows.append(row)
    return rows


def format_shapes_table(rows: list[Row], arms: list[str], command: str, time_limit: float) -> str:
    lines = [
        f"    {command}",
        "",
        f"Seconds to the first valid assembly (each passed by the full verifier), or none within "
        f"{time_limit:.0f} s (the solver's deepest state in brackets: pieces placed of K-1).",
        "",
        "| shape (voxels, box) | K | removal | " + " | ".join(arms) + " |",
        "|---|---|---|" + "---|" * len(arms),
    ]
    for r in rows:
        dims = "x".join(map(str, r.dims))
        cells = " | ".join(r.cells[a].text(r.pieces) for a in arms)
        lines.append(f"| {r.shape} ({r.voxels}, {dims}) | {r.pieces} | {r.removal} | {cells} |")
    return "\n".join(lines) + "\n"


def rows_json(rows: list[Row]) -> list[dict]:
    return [{**asdict(r), "cells": {a: asdict(c) for a, c in r.cells.items()}} for r in rows]
