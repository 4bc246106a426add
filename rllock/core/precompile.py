"""Compile the numba code once, at install time, into numba's on-disk cache.

On a cold cache the sampler, the checkers and the winding numbers take minutes to compile, and that
time would land inside the first command's `--time-limit`: a fresh install's first `solve` could spend
its whole time limit compiling. `scripts/install.sh` runs this module after installing, so commands and
tests start from compiled code; with a warm cache it only loads it. Each call below goes through the
public functions the search, MCTS and the mesh loader use, with their argument types: numba compiles
one version per type signature. The compiled functions they call (the proposals of `compiled_proposals`,
the interlocking test of `compiled_interlocking`) are compiled into them, with the same types.
"""

from __future__ import annotations

import logging
import time
from dataclasses import fields, replace
from typing import Any

import numpy as np

from rllock.core.env import (
    Task,
    apply_chunk,
    candidates_many,
    initial_state,
    make_task,
    rejections,
    sample_accepted,
    tightest_subset,
)
from rllock.core.winding import build_tree, winding_numbers

log = logging.getLogger(__name__)


def _layouts(task: Task) -> list[Task]:
    """`task` with its tables as built and read-only (as they come through Ray's object store to an
    actor): each layout is a type signature of its own to numba."""

    def frozen(array: np.ndarray) -> np.ndarray:
        array = array.copy()
        array.flags.writeable = False
        return array

    topology = task.topology
    tables: dict[str, Any] = {
        f.name: frozen(v) for f in fields(topology) if isinstance(v := getattr(topology, f.name), np.ndarray)
    }
    return [task, replace(task, topology=replace(topology, **tables))]


def compile_all() -> float:
    """Compile (or load from the cache) every compiled function for both removal modes; the seconds."""
    start = time.perf_counter()
    for removal in ("straight", "path"):
        for task in _layouts(make_task("cube4", 6, removal=removal)):
            state = initial_state(task)
            for closed_share, thin, wide in ((0.0, 0, False), (0.5, 1, True), (1.0, 0, False)):
                accepted = sample_accepted(
                    task, state, seed=0, num_samples=8, closed_share=closed_share, thin=thin, wide_seeds=wide
                )
            if len(accepted):
                state = apply_chunk(state, tightest_subset(task, state, accepted, 4, seed=0)[0])
            rejections(task, state, seed=0, num_samples=4)
            for parallel in (True, False):
                candidates_many(
                    task, [state], np.array([0]), num_samples=4, max_candidates=2, parallel=parallel
                )
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float64)
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.int64)
    winding_numbers(build_tree(vertices, faces), np.full((1, 3), 0.25))
    return time.perf_counter() - start


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    log.info("rllock: compiled code ready (%.1f s)", compile_all())
