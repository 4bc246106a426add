"""One restart of the search: a depth-first search with lookahead from the root (or a given state), its
nodes' children sampled (on threads when a sample is long enough to pay for the hand-over) and ordered,
and the counters a running search keeps. Restarts (`rllock.search.restarts`), dives
(`rllock.search.dives`) and the solver (`rllock.search.solver`) are built from it."""

from __future__ import annotations

import copy
import threading
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field, fields, replace
from typing import Any, NamedTuple

import numpy as np

from rllock.core.env import (
    State,
    Task,
    apply_chunk,
    distinct_subset,
    initial_state,
    sample_accepted,
    tightest_subset,
)
from rllock.search.search_config import SearchConfig

# How often a running search reports its progress, in seconds.
PROGRESS_EVERY = 0.5


@dataclass
class SearchStats:
    """What a search has done so far, updated in place while it runs (for progress and for saying what
    a search that found nothing reached)."""

    expansions: int = 0
    restarts: int = 0
    dives: int = 0  # the restarts that dived (`SearchConfig.dive_share`)
    deepest: State | None = None  # a state with the most pieces placed so far
    reported: float = field(default=0.0, repr=False)  # when progress was last reported

    @property
    def placed(self) -> int:
        """The most pieces placed in any state reached."""
        return 0 if self.deepest is None else self.deepest.placed

    def reached(self, state: State) -> None:
        if self.deepest is None or state.placed > self.deepest.placed:
            self.deepest = state


def never() -> bool:
    return False


Record = Callable[[State, float], None]
"""Takes each state the search leaves (its subtree done, its restart cut short, or on an assembly's path),
with its lookahead share (`Child.share`): where a guide network's training (`rllock.actors.guide_actor`) picks
the states it labels."""


class Child(NamedTuple):
    """A node's child as the search keeps it: the state, its own candidate chunks when the lookahead
    sampled them, and its lookahead share (its accepted continuations over the most among its
    siblings; 0 without lookahead)."""

    state: State
    grand: np.ndarray | None
    share: float


# A node's children are sampled on threads only when one sample takes at least this long: shorter ones
# cost about as much to hand over to a thread as to run.
THREADED_FROM_SECONDS = 0.5e-3


@dataclass
class SamplingPool:
    """The threads a node's children are sampled on, a running mean of one sample's seconds, and the
    seconds of the samples begun since the first ended (`counted` from `counting_since`; each
    sample's CPU time on the thread that ran it: the first loads the compiled sampler, most of a
    second where nothing has yet). A portfolio (`rllock.search.portfolio`) turns its worker 0's
    threads off (`allowed`) while the other workers have the cores; the figures are kept either way.
    `guessed` counts the samples run ahead for a guessed next node (`_Expander`), `reused` those of
    them the search then took."""

    executor: ThreadPoolExecutor
    threads: int
    sample_seconds: float = 0.0
    allowed: bool = True
    guessed: int = 0
    reused: int = 0
    counting_since: float | None = None  # `time.monotonic()`
    counted: float = 0.0
    local: threading.local = field(default_factory=threading.local)

    @classmethod
    def start(cls, threads: int, allowed: bool = True) -> SamplingPool:
        return cls(ThreadPoolExecutor(threads, "rllock-lookahead"), threads, allowed=allowed)

    def own(self, task: Task) -> Task:
        """`task` with this thread's own copy of its topology tables. The compiled sampler counts
        references to the arrays it is given with atomic increments; two threads sharing one array make
        its count's cache line bounce between the cores, which costs every sample CPU time."""
        held = getattr(self.local, "held", None)
        if held is None or held[0] is not task:
            topology = task.topology
            copies: dict[str, Any] = {  # the arrays; n_lines, an int, stays
                f.name: value.copy()
                for f in fields(topology)
                if isinstance(value := getattr(topology, f.name), np.ndarray)
            }
            held = self.local.held = (task, replace(task, topology=replace(topology, **copies)))
        return held[1]

    def worth_it(self, samples: int) -> bool:
        return self.allowed and samples > 1 and self.sample_seconds >= THREADED_FROM_SECONDS

    def took(self, seconds: float, began: float) -> None:
        """A sample begun at `began` (`time.monotonic()`) took `seconds` of its thread's CPU time."""
        # Called from the pool's threads at once: an update lost between two of them only blurs a mean.
        self.sample_seconds += 0.1 * (seconds - self.sample_seconds)
        if self.counting_since is None:
            self.counting_since = time.monotonic()
        elif began >= self.counting_since:
            self.counted += seconds


@dataclass
class _Guess:
    """Samples run ahead for the children `chunks` make of `parent`, with the seeds the search will
    draw for them if `parent` is the next node it expands: child index -> its sample's future."""

    chunks: np.ndarray
    seeds: list[int]
    parent: State
    futures: dict[int, Future]


@dataclass
class _Expander:
    """Expands the nodes of one restart: samples a node's children (counting expansions, reporting
    progress) and orders them under lookahead."""

    task: Task
    rng: np.random.Generator
    config: SearchConfig
    target: int
    stats: SearchStats
    report: Callable[[SearchStats], None] | None
    pool: SamplingPool | None = None
    expansions: int = 0
    guess: _Guess | None = None

    def sample(self, state: State) -> tuple[np.ndarray, int]:
        """(up to `children` distinct accepted chunks, how many were accepted)."""
        return self._chunks(state, self._enter(state))

    def sample_all(self, states: list[State], chunks: np.ndarray) -> list[tuple[np.ndarray, int]]:
        """`sample` of each of `states` (the children `chunks` make), on the lookahead's threads when
        there are some and the samples are long enough: their seeds are drawn here first, in order, so
        the result is the same as one after another. Samples run ahead for these very children and
        seeds (`_guess_next`) are taken as they are."""
        seeds = [self._enter(s) for s in states]
        guess, self.guess = self.guess, None
        ready = guess.futures if guess is not None and guess.chunks is chunks and guess.seeds == seeds else {}
        if self.pool is not None:
            self.pool.reused += len(ready)
        if self.pool is None or not self.pool.worth_it(len(states)):
            return [
                ready[i].result() if i in ready else self._chunks(s, seed)
                for i, (s, seed) in enumerate(zip(states, seeds))
            ]
        pool = self.pool
        futures = [
            ready.get(i) or pool.executor.submit(self._chunks, s, seed)
            for i, (s, seed) in enumerate(zip(states, seeds))
        ]
        waiting = set(futures)
        while waiting:
            if len(waiting) < pool.threads:
                self._guess_next(states, futures, len(waiting))
            ahead: set[Future] = (
                {f for f in self.guess.futures.values() if not f.done()} if self.guess else set()
            )
            wait(waiting | ahead, return_when=FIRST_COMPLETED)
            waiting = {f for f in waiting if not f.done()}
        return [f.result() for f in futures]

    def _guess_next(self, states: list[State], futures: list[Future], busy: int) -> None:
        """Give the threads this node's samples leave idle the samples of the node the search will most
        likely expand next: the child `children_of` will put last among those sampled so far
        (`pop_rank`), seeded from a copy of the generator as the search will seed them if that child is
        the one it takes. In the remainder's order that child is known once every child before it is
        sampled, and only then is it guessed (threads finish out of order under load). A wrong guess,
        in the other order, costs the samples it started, each on a thread that was idle when it started
        (the next node's samples may wait for them)."""
        done = [(i, f.result()[1]) for i, f in enumerate(futures) if f.done() and len(f.result()[0])]
        if not done:
            return
        by_remainder = self.config.by_remainder(self.task, self.task.pieces - states[0].placed)
        best = max(done, key=lambda d: pop_rank(d[0], d[1], by_remainder))[0]
        if by_remainder and not all(f.done() for f in futures[:best]):
            return  # an earlier child may still find a continuation: wait until the guess is certain
        grand = futures[best].result()[0]
        if states[best].placed + 1 >= self.target:
            return  # the next node is an assembly or samples nothing
        if self.guess is None or self.guess.chunks is not grand:
            rng = copy.deepcopy(self.rng)
            self.guess = _Guess(grand, [int(rng.integers(1 << 31)) for _ in grand], states[best], {})
        guess, pool = self.guess, self.pool
        assert pool is not None
        busy += sum(not f.done() for f in guess.futures.values())
        while busy < pool.threads and len(guess.futures) < len(guess.chunks):
            i = len(guess.futures)
            kid = apply_chunk(guess.parent, guess.chunks[i])
            guess.futures[i] = pool.executor.submit(self._chunks, kid, guess.seeds[i])
            pool.guessed += 1
            busy += 1

    def _enter(self, state: State) -> int:
        """Counts the expansion of `state` (progress reported when due); its sampling seed."""
        stats = self.stats
        self.expansions += 1
        stats.expansions += 1
        stats.reached(state)
        now = time.monotonic()
        if self.report is not None and now - stats.reported >= PROGRESS_EVERY:
            stats.reported = now
            self.report(stats)
        return int(self.rng.integers(1 << 31))

    def _chunks(self, state: State, seed: int) -> tuple[np.ndarray, int]:
        config = self.config
        task = self.task if self.pool is None else self.pool.own(self.task)
        deep = config.deep(task)
        # CPU time of this thread: a sample's wall time also counts the moments another thread or process
        # had the core, which made two threads look busier than they were (a share over 1 was seen).
        began, started = time.monotonic(), time.thread_time()
        accepted = sample_accepted(
            task,
            state,
            seed=seed,
            num_samples=config.samples_per_node,
            closed_share=config.share_for(task),
            thin=int(deep),
            wide_seeds=deep,
        )
        if self.pool is not None:
            self.pool.took(time.thread_time() - started, began)
        if deep and len(accepted):
            surface = config.surface(task)
            return tightest_subset(task, state, accepted, config.children, seed, surface), len(accepted)
        return distinct_subset(accepted, config.children, seed), len(accepted)

    def children_of(self, state: State, chunks: np.ndarray) -> list[Child]:
        """Children in pop order (best last); under lookahead their own candidates are attached and
        those with none dropped."""
        kids = [apply_chunk(state, c) for c in chunks]
        if not self.config.lookahead or state.placed + 1 == self.target:
            return [Child(k, None, 0.0) for k in kids]
        scored = []
        config, task = self.config, self.task
        by_remainder = config.by_remainder(task, task.pieces - 1 - state.placed)
        for i, (kid, (grand, count)) in enumerate(zip(kids, self.sample_all(kids, chunks))):
            if len(grand):
                scored.append((pop_rank(i, count, by_remainder), count, kid, grand))
        scored.sort(key=lambda t: t[0])
        most = max((count for _, count, _, _ in scored), default=1)
        return [Child(kid, grand, count / most) for _, count, kid, grand in scored]


def pop_rank(index: int, count: int, by_remainder: bool) -> tuple[int, int]:
    """Where the child made by a node's `index`-th chunk, with `count` accepted continuations, goes in
    its node's pop order (the greatest is tried first): in the remainder's order the first chunk first
    (in deep mode the chunks come best first by its judgement, `tightest_subset`), else the most
    continuations first, the last such of equal counts."""
    return (-index if by_remainder else count, index)


def dfs(
    task: Task,
    rng: np.random.Generator,
    config: SearchConfig,
    budget: int,
    deadline: float,
    target: int,
    stats: SearchStats,
    stop: Callable[[], bool] = never,
    report: Callable[[SearchStats], None] | None = None,
    record: Record | None = None,
    start: State | None = None,
    pool: SamplingPool | None = None,
):
    """One restart: DFS from the root (or `start`) for at most `budget` expansions until a state with
    `target` placed pieces, the deadline, or `stop()`. Returns (that state or None, expansions used); `stats`
    counts the expansions and keeps the deepest state, and `report(stats)` is called every
    PROGRESS_EVERY seconds; `record` takes every state the search leaves (`Record`)."""
    nodes = _Expander(task, rng, config, target, stats, report, pool)
    root = initial_state(task) if start is None else start
    stack = [nodes.children_of(root, nodes.sample(root)[0])]
    path = [Child(root, None, 1.0)]  # the child each stack level holds the children of
    while stack:
        if nodes.expansions >= budget or time.monotonic() > deadline or stop():
            _left(path, record)
            return None, nodes.expansions
        if not stack[-1]:
            stack.pop()
            _left(path[-1:], record)
            path.pop()
            continue
        child = stack[-1].pop()
        if child.state.placed == target:
            _left(path, record)
            return child.state, nodes.expansions
        grand = nodes.sample(child.state)[0] if child.grand is None else child.grand
        stack.append(nodes.children_of(child.state, grand))
        path.append(child)
    return None, nodes.expansions


def _left(states: list[Child], record: Record | None) -> None:
    """The search leaves `states` (a subtree done, a restart cut short, or an assembly's path)."""
    if record is not None:
        for c in states:
            record(c.state, c.share)


def expand(task: Task, state: State, *, seed: int, config: SearchConfig = SearchConfig()) -> list[Child]:
    """The children of `state` as the search makes them (sampled, the lookahead's count kept as their
    share, those with no continuation dropped), in pop order: best last."""
    nodes = _Expander(task, np.random.default_rng(seed), config, task.pieces - 1, SearchStats(), None)
    return nodes.children_of(state, nodes.sample(state)[0])
