"""Several searches at once, one process each: a portfolio of seeds (`rllock solve --workers N`).

The search's run times are heavy-tailed (`rllock.search.solver`): one seed may need ten times as long as
another on the same task. N seeds side by side, the first assembly taken, cut that tail, so on hard cells
N workers gain more than their share of a single search's time. Worker 0 runs the given seed, so one
worker is the plain search; worker i > 0 runs `derive_seed(seed, i)`.

On one machine worker 0 runs in this process, as a thread (it starts at once, with what this process
has compiled), and may sample a node's children on several threads (`threads`, `solve --threads`: the
same search node for node, sooner); the others are spawned processes. Measured on 2 cores: two searches
side by side each run as fast as one alone, while one search on two threads runs 1.5-1.7x as fast
(1.4-5.6 ms a node expansion; 1.0x at 0.34 ms, where the threads are left unused): where run times are spread,
a second seed gains more than a second thread; where they are not, the thread gains more.

Workers put what they find and their progress on a queue; the parent keeps the distinct assemblies and
stops every worker (an event they poll between node expansions) when it has what it wants, at the time
limit or when asked. Workers ignore Ctrl-C: the parent's stop reaches them through that event.

The workers are local processes (`_LocalCrew`), or Ray actors of one CPU each on the cluster the caller
has joined (`_RayCrew`, `rllock solve --address`): the same messages on a Ray queue, and a flag actor for
the event, which the workers read at most every STOP_POLL_SECONDS.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import queue as queues
import signal
import threading
import time
from collections.abc import Callable, Generator
from typing import Any

from rllock.core.env import Task, assembly_key
from rllock.search.base import derive_seed
from rllock.search.solver import PROGRESS_EVERY, Found, SearchConfig, SearchStats, _never, search

log = logging.getLogger(__name__)

JOIN_SECONDS = 2.0  # a worker polls the stop event between node expansions; then it is terminated


def worker_seed(seed: int, worker: int) -> int:
    """The seed worker `worker` of a portfolio seeded `seed` searches with (worker 0: `seed` itself)."""
    return seed if worker == 0 else derive_seed(seed, worker)


def _work(
    out: Any,
    halt: Any,
    task: Task,
    seed: int,
    time_limit: float,
    config: SearchConfig,
    guide: Any,
    worker: int,
    threads: int,
) -> None:
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
            threads=threads,
        )
        for f in found:
            out.put(("found", worker, f))
    except Exception as exc:
        out.put(("error", worker, f"{type(exc).__name__}: {exc}"))
    finally:
        out.put(("done", worker, stats))


def _work_locally(*args: Any) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _work(*args)


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
    on_ray: bool = False,
    threads: int = 1,
) -> Generator[Found, None, None]:
    """`solver.search` in `workers` processes (module docstring), or with `on_ray` in as many Ray actors on
    the cluster this process has joined: yields the distinct assemblies in the order they arrive, `seconds`
    counted by the parent, until the time limit or `stop()`; the caller stops it by closing the generator
    (or breaking out of its loop). `stats` sums the workers'. `threads`: worker 0's sampling threads on
    this machine (a Ray worker has its one CPU)."""
    stats = SearchStats() if stats is None else stats
    # Each worker's arguments of `_work` after the queue and the stop flag, which its crew adds.
    first = 1 if on_ray else threads
    jobs = [
        (task, worker_seed(seed, i), time_limit, config, guide, i, first if i == 0 else 1)
        for i in range(workers)
    ]
    crew: _LocalCrew | _RayCrew = _RayCrew(jobs) if on_ray else _LocalCrew(jobs)
    start = time.monotonic()
    deadline, last = start + time_limit, start
    latest: dict[int, SearchStats] = {}
    done: set[int] = set()
    seen: set[bytes] = set()
    try:
        crew.start()
        while len(done) < workers and time.monotonic() < deadline and not stop():
            message = crew.get(timeout=0.2)
            if message is None:
                crew.check_alive(done)
                continue
            kind, worker, payload = message
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
        crew.halt()
        end = time.monotonic() + JOIN_SECONDS
        # The queue is read while the workers stop: a worker blocked on a full queue would never exit.
        while crew.running() and time.monotonic() < end:
            message = crew.get(timeout=0.1)
            if message is not None and message[0] in ("progress", "done"):
                latest[message[1]] = message[2]
        crew.close()
        merge_stats(list(latest.values()), stats)


class _LocalCrew:
    """Worker 0 as a thread of this process (it starts at once, with what this process has compiled), the
    others as spawned processes; a multiprocessing queue and event."""

    def __init__(self, jobs: list[tuple]) -> None:
        context = mp.get_context("spawn")  # forking a process that holds numba or JAX state is not safe
        self.out, self.event = context.Queue(), context.Event()
        self.first = threading.Thread(target=_work, args=(self.out, self.event, *jobs[0]), daemon=True)
        self.processes = [
            context.Process(target=_work_locally, args=(self.out, self.event, *job), daemon=True)
            for job in jobs[1:]
        ]

    def start(self) -> None:
        self.first.start()
        for p in self.processes:
            p.start()

    def get(self, timeout: float) -> tuple | None:
        try:
            return self.out.get(timeout=timeout)
        except queues.Empty:
            return None

    def check_alive(self, done: set[int]) -> None:
        """A worker that died without saying so (killed, out of memory) is an error, not a silent hang."""
        for i, p in enumerate(self.processes, start=1):
            if i not in done and p.exitcode is not None and p.exitcode != 0:
                raise RuntimeError(f"search worker {i} ended with exit code {p.exitcode}")

    def halt(self) -> None:
        self.event.set()

    def running(self) -> bool:
        return self.first.is_alive() or any(p.is_alive() for p in self.processes)

    def close(self) -> None:
        """Workers that did not stop in time are terminated; worker 0 stops at its next node."""
        for p in self.processes:
            if p.is_alive():
                p.terminate()
            p.join(timeout=1.0)
        self.first.join(timeout=JOIN_SECONDS)


# How often a Ray worker asks the flag actor whether to stop: a remote call per node expansion would cost
# more than the expansion.
STOP_POLL_SECONDS = 0.5


class _PolledFlag:
    """`is_set` of a flag actor, asked at most every STOP_POLL_SECONDS."""

    def __init__(self, flag: Any) -> None:
        self.flag, self.asked, self.answer = flag, 0.0, False

    def is_set(self) -> bool:
        import ray

        now = time.monotonic()
        if not self.answer and now - self.asked >= STOP_POLL_SECONDS:
            self.asked = now
            self.answer = ray.get(self.flag.is_set.remote())
        return self.answer


class _RayCrew:
    """Workers as Ray actors of one CPU each, wherever the cluster places them; a Ray queue and a flag
    actor. The nodes they run on are logged."""

    def __init__(self, jobs: list[tuple]) -> None:
        import ray
        from ray.util.queue import Queue

        self.jobs = jobs
        self.out = Queue(actor_options={"num_cpus": 0})
        # Ray types an actor's methods loosely (no `.remote` on them), so the handles are Any here.
        self.flag: Any = ray.remote(num_cpus=0)(_Flag).remote()
        worker: Any = ray.remote(num_cpus=1)(_RayWorker)
        self.actors: list[Any] = [worker.remote() for _ in jobs]
        self.runs: list[Any] = []

    def start(self) -> None:
        import ray

        nodes = ray.get([a.node.remote() for a in self.actors])
        log.info("search workers on %d Ray node(s): %s", len(set(nodes)), ", ".join(nodes))
        self.runs = [a.run.remote(self.out, self.flag, *job) for a, job in zip(self.actors, self.jobs)]

    def get(self, timeout: float) -> tuple | None:
        from ray.util.queue import Empty

        try:
            return self.out.get(timeout=timeout)
        except Empty:
            return None

    def check_alive(self, done: set[int]) -> None:
        """A worker whose actor died (its node lost, killed) is an error, not a silent hang."""
        import ray

        finished, _ = ray.wait(self.runs, num_returns=len(self.runs), timeout=0)
        for ref in finished:
            i = self.runs.index(ref)
            if i not in done:
                try:
                    ray.get(ref)
                except ray.exceptions.RayError as exc:
                    raise RuntimeError(f"search worker {i} failed on Ray: {type(exc).__name__}") from None

    def halt(self) -> None:
        self.flag.set.remote()

    def running(self) -> bool:
        import ray

        return bool(self.runs) and len(ray.wait(self.runs, num_returns=len(self.runs), timeout=0)[1]) > 0

    def close(self) -> None:
        import ray

        for a in [*self.actors, self.flag]:
            ray.kill(a)
        self.out.shutdown()


class _Flag:
    def __init__(self) -> None:
        self.value = False

    def set(self) -> None:
        self.value = True

    def is_set(self) -> bool:
        return self.value


class _RayWorker:
    def node(self) -> str:
        import ray

        return ray.get_runtime_context().get_node_id()

    def run(self, out: Any, flag: Any, *job: Any) -> None:
        _work(out, _PolledFlag(flag), *job)
