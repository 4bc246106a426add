"""The search solver: randomized depth-first search with backtracking and restarts over sampled chunks.

No learning. Each node samples raw chunks and keeps up to `children` distinct accepted ones in random
order; the search backtracks when a node's children are exhausted. Search trees for this problem are
heavy-tailed (one bad early piece can doom a whole subtree), so the search restarts from the root after
a budget of node expansions that follows the Luby sequence (1, 1, 2, 1, 1, 2, 4, ...) times
`restart_base`: short runs most of the time, occasionally long ones, which is within a log factor of
the best fixed budget without knowing it.

Searches fail late, when what remains of the shape has thinned into strands; in deep mode (the
default at every K, `SearchConfig.deep_from`) the search keeps the remaining volume compact (wide
seeds, thin growth, children after which the remainder's surface grows least, or under path removal with
the smallest cut) and restarts less often.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Generator
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from rllock.core.env import State, Task, assembly_key, final_labels
from rllock.core.feasibility import check_feasible
from rllock.search.dfs import Record, SamplingPool, SearchStats, dfs, never
from rllock.search.dives import DIVE_STREAM, RestartSequence, best_dive, dive_allowance, dive_depth
from rllock.search.restarts import luby
from rllock.search.search_config import SearchConfig

if TYPE_CHECKING:  # the guide brings JAX; the plain search starts without it
    from rllock.search.guide import Guide


@dataclass(frozen=True)
class Found:
    labels: np.ndarray  # int grid [x, y, z], 1..K
    seconds: float  # time since the previous assembly (or the start)
    expansions: int  # node expansions since the previous assembly
    seed: int  # the seed of the search that found it (its run with that seed finds it again)


def search(
    task: Task,
    *,
    seed: int,
    time_limit: float,
    config: SearchConfig = SearchConfig(),
    stats: SearchStats | None = None,
    stop: Callable[[], bool] = never,
    report: Callable[[SearchStats], None] | None = None,
    guide: Guide | None = None,
    record: Record | None = None,
    threads: int = 1,
    pool: SamplingPool | None = None,
) -> Generator[Found, None, None]:
    """Yield distinct valid assemblies (checked by the compiled checkers; the caller verifies before
    writing) until the time limit or `stop()`. Same seed, same sequence. `stats`, when given, is kept up
    to date (and passed to `report` every PROGRESS_EVERY seconds). A `guide` network picks where
    restarts begin (`SearchConfig.dives`); `record`
    takes the states the search leaves with their lookahead shares. A node's children are sampled on
    `threads` threads, or on a `pool` the caller owns (and shuts down). A task that provably has no
    assembly is an error at once (`rllock.core.feasibility`)."""
    if threads < 1:
        raise ValueError(f"threads must be at least 1, got {threads}")
    if threads > 1 and pool is not None:
        raise ValueError("give threads or a pool, not both")
    check_feasible(task)
    own = SamplingPool.start(threads) if threads > 1 else None
    try:
        yield from _search(task, seed, time_limit, config, stats, stop, report, guide, record, own or pool)
    finally:
        if own is not None:
            own.executor.shutdown(cancel_futures=True)


def _search(
    task: Task,
    seed: int,
    time_limit: float,
    config: SearchConfig,
    stats: SearchStats | None,
    stop: Callable[[], bool],
    report: Callable[[SearchStats], None] | None,
    guide: Guide | None,
    record: Record | None,
    pool: SamplingPool | None,
) -> Generator[Found, None, None]:
    stats = SearchStats() if stats is None else stats
    start = time.monotonic()
    deadline = start + time_limit
    seen: set[bytes] = set()
    kept: list[tuple[float, State]] = []  # dive states not yet taken, with their values (`best_dive`)
    solver = RestartSequence(np.random.default_rng(seed))
    diver = RestartSequence(np.random.default_rng([seed, DIVE_STREAM]))
    depth = 0 if guide is None else dive_depth(task, guide)
    dives = config.dives > 1 and depth >= 1
    unit = config.restart_unit(task, task.pieces - 1)
    last = start
    while time.monotonic() < deadline and not stop():
        allowance = dive_allowance(config, unit, solver.used)
        diving = dives and diver.used + diver.planned(unit, config.dives * depth) <= allowance
        run = diver if diving else solver
        run.restarts += 1
        stats.restarts += 1
        stats.dives += diving
        budget = unit * luby(run.restarts)
        begin, spent = (
            best_dive(task, run.rng, config, budget, deadline, stats, stop, report, guide, pool, kept)
            if diving
            else (None, 0)
        )
        state, expansions = dfs(
            task,
            run.rng,
            config,
            budget,
            deadline,
            task.pieces - 1,
            stats,
            stop,
            report,
            record,
            begin,
            pool,
        )
        run.used += spent + expansions
        run.dived += spent
        run.ran += diving
        if state is None:
            continue
        stats.reached(state)
        labels = final_labels(task, state)
        key = assembly_key(labels)
        if key in seen:
            continue
        seen.add(key)
        now = time.monotonic()
        yield Found(task.topology.to_grid(labels), now - last, solver.used + diver.used, seed)
        last = now
        for sequence in (solver, diver):
            sequence.restarts, sequence.used = 0, 0


def solve(
    task: Task,
    *,
    count: int = 1,
    time_limit: float = 60.0,
    seed: int = 0,
    config: SearchConfig = SearchConfig(),
    guide: Guide | None = None,
    threads: int = 1,
) -> list[np.ndarray]:
    """Up to `count` distinct assemblies of `task` found by the search within `time_limit` seconds, as
    label grids [x, y, z] (1..K, in disassembly order), each passed by the full verifier. `guide`: a
    guide network (`rllock.search.guide`) that picks where the search's restarts begin. `threads`: a
    node's children are sampled on this many threads (the same search, node for node, sooner on as many
    cores)."""
    from rllock.core.verifier import verify_labels

    found = []
    for f in search(task, seed=seed, time_limit=time_limit, config=config, guide=guide, threads=threads):
        if not verify_labels(f.labels, task.removal).valid:
            raise AssertionError("the search returned an assembly the verifier rejects")
        found.append(f.labels)
        if len(found) >= count:
            break
    return found
