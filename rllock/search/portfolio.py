"""Several searches at once, one process each: a portfolio of seeds (`rllock solve --workers N`).

The search's run times are heavy-tailed (`rllock.search.solver`): one seed may need ten times as long as
another on the same task. N seeds side by side, the first assembly taken, cut that tail, so on hard cells
N workers gain more than their share of a single search's time. Worker 0 runs the given seed, so one
worker is the plain search; worker i > 0 runs `derive_seed(seed, i)`.

Workers put what they find and their progress on a queue; the parent keeps the distinct assemblies and
stops every worker (an event they poll between node expansions) when it has what it wants, at the time
limit or when asked. Workers ignore Ctrl-C: the parent's stop reaches them through that event.
"""

from __future__ import annotations

import multiprocessing as mp
import queue as queues
import signal
import time
from collections.abc import Callable, Generator
from typing import Any

from rllock.core.env import Task, assembly_key
from rllock.search.base import derive_seed
from rllock.search.solver import PROGRESS_EVERY, Found, SearchConfig, SearchStats, _never, search

JOIN_SECONDS = 2.0  # a worker polls the stop event between node expansions; then it is terminated


def worker_seed(seed: int, worker: int) -> int:
    """The seed worker `worker` of a portfolio seeded `seed` searches with (worker 0: `seed` itself)."""
    return seed if worker == 0 else derive_seed(seed, worker)


def _work(
    task: Task,
    seed: int,
    time_limit: float,
    config: SearchConfig,
    guide: Any,
    out: Any,
    halt: Any,
    worker: int,
) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    stats = SearchStats()
    try:
        found = search(
            task,
            seed=seed,
            time_limit=time_limit,
            config=config,
            stats=stats,
            stop=halt.is_set,
            report=lambda s: out.put(("progress", worker, s)),
            guide=guide,
        )
        for f in found:
            out.put(("found", worker, f))
    except Exception as exc:
        out.put(("error", worker, f"{type(exc).__name__}: {exc}"))
    finally:
        out.put(("done", worker, stats))


def merge_stats(parts: list[SearchStats], into: SearchStats) -> None:
    """`into` becomes the workers' stats together: their expansions and restarts summed, the deepest state."""
    into.expansions = sum(s.expansions for s in parts)
    into.restarts = sum(s.restarts for s in parts)
    for s in parts:
        if s.deepest is not None:
            into.reached(s.deepest)


def portfolio_search(
    task: Task,
    *,
    seed: int,
    workers: int,
    time_limit: float,
    config: SearchConfig = SearchConfig(),
    stats: SearchStats | None = None,
    stop: Callable[[], bool] = _never,
    report: Callable[[SearchStats], None] | None = None,
    guide: Any = None,
) -> Generator[Found, None, None]:
    """`solver.search` in `workers` processes (module docstring): yields the distinct assemblies in the
    order they arrive, `seconds` counted by the parent, until the time limit or `stop()`; the caller
    stops it by closing the generator (or breaking out of its loop). `stats` sums the workers'."""
    stats = SearchStats() if stats is None else stats
    context = mp.get_context("spawn")  # forking a process that holds numba or JAX state is not safe
    out, halt = context.Queue(), context.Event()
    processes = [
        context.Process(
            target=_work,
            args=(task, worker_seed(seed, i), time_limit, config, guide, out, halt, i),
            daemon=True,
        )
        for i in range(workers)
    ]
    start = time.monotonic()
    deadline, last = start + time_limit, start
    latest: dict[int, SearchStats] = {}
    done: set[int] = set()
    seen: set[bytes] = set()
    try:
        for p in processes:
            p.start()
        while len(done) < workers and time.monotonic() < deadline and not stop():
            try:
                kind, worker, payload = out.get(timeout=0.2)
            except queues.Empty:
                _check_alive(processes, done)
                continue
            if kind == "found":
                key = assembly_key(payload.labels)
                if key not in seen:
                    seen.add(key)
                    now = time.monotonic()
                    yield Found(payload.labels, now - last, payload.expansions, payload.seed)
                    last = now
            elif kind == "error":
                raise RuntimeError(f"search worker {worker} failed: {payload}")
            else:
                latest[worker] = payload
                if kind == "done":
                    done.add(worker)
                merge_stats(list(latest.values()), stats)
                if report is not None and time.monotonic() - stats.reported >= PROGRESS_EVERY:
                    stats.reported = time.monotonic()
                    report(stats)
    finally:
        halt.set()
        _drain(processes, out, latest)
        merge_stats(list(latest.values()), stats)


def _check_alive(processes: list, done: set[int]) -> None:
    """A worker that died without saying so (killed, out of memory) is an error, not a silent hang."""
    for i, p in enumerate(processes):
        if i not in done and p.exitcode is not None and p.exitcode != 0:
            raise RuntimeError(f"search worker {i} ended with exit code {p.exitcode}")


def _drain(processes: list, out: Any, latest: dict[int, SearchStats]) -> None:
    """Wait for the workers to stop, keeping their last stats; those that do not stop are terminated.
    The queue is read while waiting: a worker blocked on a full queue would never exit."""
    end = time.monotonic() + JOIN_SECONDS
    while any(p.is_alive() for p in processes) and time.monotonic() < end:
        try:
            kind, worker, payload = out.get(timeout=0.1)
        except queues.Empty:
            continue
        if kind in ("progress", "done"):
            latest[worker] = payload
    for p in processes:
        if p.is_alive():
            p.terminate()
        p.join(timeout=1.0)
