"""Several searches at once: a portfolio of seeds (`rllock solve --workers N`).

The search's run times are heavy-tailed (`rllock.search.solver`): one seed may need ten times as long as
another on the same task. N seeds side by side, the first assembly taken, cut that tail, so on hard cells
N workers gain more than their share of a single search's time. Worker 0 runs the given seed, so one
worker is the plain search; worker i > 0 runs `derive_seed(seed, i)`.

On one machine worker 0 runs in this process, as a thread (it starts at once, with what this process has
compiled); the others are spawned processes. Worker 0 may also sample a node's children on threads (the same
search node for node, sooner: `dfs.SamplingPool`). A second seed pays by the spread of run times, a second
thread surely but by less, and by how busy the search keeps it: two threads gain most where both are busy,
little where a node's samples are few or cheap. So worker 0 has the cores of workers 1..T-1 on T threads from
the start, and those workers (the lent ones) are not started while it has them: a spawned process's start-up
(imports, the compiled code loaded) took CPU from worker 0's threads on every seed, also where it was never
let go on. From the end of worker 0's first sample on, the crew measures how busy its threads are, the CPU
seconds of its samples over the wall time, every BALANCE_EVERY_SECONDS. Once that share is below
KEEP_WHILE_BUSY of the T threads (judged from JUDGE_AFTER_SECONDS on), the lent workers are started, each on
its core, and worker 0 samples alone for the rest of the run. The measure is a ratio of two times on one
machine, so a slower or faster machine decides alike, where a threshold on the milliseconds a sample costs
would decide differently on every machine.

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
import os
import queue as queues
import signal
import sys
import threading
import time
from collections.abc import Callable, Generator
from typing import Any

from rllock.core.env import Task, assembly_key
from rllock.search.base import derive_seed
from rllock.search.dfs import PROGRESS_EVERY, SamplingPool, SearchStats, never
from rllock.search.search_config import SearchConfig
from rllock.search.solver import Found, search

log = logging.getLogger(__name__)

JOIN_SECONDS = 2.0  # a worker polls the stop event between node expansions; then it is terminated

# Worker 0 keeps the cores of the lent workers while its threads are busy this share of the time since
# its first sample ended, judged from JUDGE_AFTER_SECONDS on: below it lie the cells where two seeds
# gained more than two threads, above it those where two threads gained more (hard cells on 2 cores).
KEEP_WHILE_BUSY = 0.80
JUDGE_AFTER_SECONDS = 2.0
BALANCE_EVERY_SECONDS = 1.0  # how often the share is looked at


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
    pool: SamplingPool | None,
) -> None:
    """Worker `worker`'s search, its assemblies and progress put on `out`, until `halt.is_set()`, which it
    asks between node expansions."""
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
            pool=pool,
        )
        for f in found:
            out.put(("found", worker, f))
    except Exception as exc:
        out.put(("error", worker, f"{type(exc).__name__}: {exc}"))
    finally:
        out.put(("done", worker, stats))


def _work_locally(out: Any, halt: Any, *job: Any) -> None:
    """`_work` in a spawned process, which also stops once its parent is gone: a parent killed outright
    can die holding the locks of the stop event and the queue, and a worker that asked them would wait
    for ever (one was found asleep, its parent init, minutes after the kill)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    watched = Orphaned(halt, _die_with_parent())
    if watched.gone():  # the parent died before the signal was asked for
        return
    try:
        _work(out, watched, *job)
    finally:
        if watched.gone():
            out.cancel_join_thread()  # nobody reads what is left: exit without waiting to send it


class Orphaned:
    """A stop event that also counts as set once this process's parent is no longer `parent`, asked
    before the event itself (whose lock a parent killed outright may still hold)."""

    def __init__(self, event: Any, parent: int):
        self.event, self.parent = event, parent

    def gone(self) -> bool:
        return os.getppid() != self.parent

    def is_set(self) -> bool:
        return self.gone() or self.event.is_set()


PR_SET_PDEATHSIG = 1  # prctl(2)


def _die_with_parent() -> int:
    """The process id of the parent that started this worker. On Linux the kernel is first asked to
    SIGKILL this worker when the thread that started it ends, so a worker does not search on, alone,
    until its time limit when its parent is killed outright (a parent already gone then: `Orphaned`)."""
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    parent = mp.parent_process()
    return parent.pid if parent is not None and parent.pid else os.getppid()


def shares_cores(busy: float, seconds: float) -> bool:
    """Whether worker 0 should go on sampling on the lent workers' cores, given the share `busy` of the
    `seconds` since its first sample ended that its threads were busy: while it is at least
    KEEP_WHILE_BUSY, judged from JUDGE_AFTER_SECONDS on. Once they went apart it is not asked again:
    alone, worker 0 cannot show what its threads would do."""
    return seconds < JUDGE_AFTER_SECONDS or busy >= KEEP_WHILE_BUSY


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
    stop: Callable[[], bool] = never,
    report: Callable[[SearchStats], None] | None = None,
    guide: Any = None,
    on_ray: bool = False,
) -> Generator[Found, None, None]:
    """`solver.search` in `workers` processes, worker 0 sharing the cores while its threads are busy (module
    docstring), or with `on_ray` in as many Ray actors of one CPU on the cluster this process has joined:
    yields the distinct assemblies in the order they arrive, `seconds` counted by the parent, until the
    time limit or `stop()`; the caller stops it by closing the generator (or breaking out of its loop).
    `stats` sums the workers'."""
    stats = SearchStats() if stats is None else stats
    # Each worker's arguments of `_work` after the queue and the stop flag, which its crew adds; worker
    # 0's sampling pool is the local crew's to add.
    jobs = [(task, worker_seed(seed, i), time_limit, config, guide, i, None) for i in range(workers)]
    crew: _LocalCrew | _RayCrew = _RayCrew(jobs) if on_ray else _LocalCrew(jobs, config.children)
    start = time.monotonic()
    deadline, last = start + time_limit, start
    latest: dict[int, SearchStats] = {}
    done: set[int] = set()
    seen: set[bytes] = set()
    try:
        crew.start()
        while len(done) < workers and time.monotonic() < deadline and not stop():
            crew.balance(done)
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
    """Worker 0 as a thread of this process (it starts at once, with what this process has compiled), on a
    sampling pool of up to `children` threads, one a worker; the others as spawned processes, the first
    of them (`lent`) started only when worker 0 gives their cores back (module docstring); a
    multiprocessing queue and a stop event."""

    def __init__(self, jobs: list[tuple], children: int) -> None:
        context = mp.get_context("spawn")  # forking a process that holds numba or JAX state is not safe
        self.out, self.event = context.Queue(), context.Event()
        threads = min(len(jobs), children)
        self.pool = SamplingPool.start(threads, allowed=threads > 1)
        self.first = threading.Thread(
            target=_work, args=(self.out, self.event, *jobs[0][:-1], self.pool), daemon=True
        )
        self.lent = threads - 1  # workers 1..lent, whose cores worker 0 takes
        self.processes = [
            context.Process(target=_work_locally, args=(self.out, self.event, *job), daemon=True)
            for job in jobs[1:]
        ]
        self.looked = 0.0  # when the share was last looked at

    def start(self) -> None:
        self.first.start()
        for p in self.processes[self.lent :]:
            p.start()

    def balance(self, done: set[int]) -> None:
        """Every BALANCE_EVERY_SECONDS once worker 0's first sample is over: worker 0 goes on with the lent
        workers' cores, or gives them back for good, by how busy its threads have been since
        (`shares_cores`); at once when it is done."""
        now, pool = time.monotonic(), self.pool
        if not pool.allowed:
            return
        if 0 in done:
            self.give_back("worker 0 has ended")
            return
        since = pool.counting_since
        if since is None or now - self.looked < BALANCE_EVERY_SECONDS:
            return
        self.looked = now
        busy = pool.counted / max(now - since, 1e-9) / pool.threads
        log.debug("worker 0's %d threads busy %.0f%% of %.1f s", pool.threads, 100 * busy, now - since)
        if not shares_cores(busy, now - since):
            self.give_back(f"worker 0's {pool.threads} threads busy {busy:.0%} of the time")

    def give_back(self, why: str) -> None:
        """The lent workers start, each on its core, and worker 0 samples alone, for good."""
        self.pool.allowed = False
        for p in self.processes[: self.lent]:
            p.start()
        log.info("%s: every worker searches on a core of its own", why)

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
            if p.pid is not None:  # a lent worker is started only if worker 0 gave its core back
                p.join(timeout=1.0)
        self.first.join(timeout=JOIN_SECONDS)
        self.pool.executor.shutdown(cancel_futures=True)


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

    def balance(self, done: set[int]) -> None:
        """Nothing to share: each Ray worker has its one CPU."""

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
