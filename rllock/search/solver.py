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

import copy
import threading
import time
from collections.abc import Callable, Generator
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field, fields, replace
from typing import TYPE_CHECKING, Any, Literal, NamedTuple

import numpy as np

from rllock.core.env import (
    State,
    Task,
    apply_chunk,
    assembly_key,
    distinct_subset,
    final_labels,
    initial_state,
    sample_accepted,
    tightest_subset,
)
from rllock.core.feasibility import check_feasible

if TYPE_CHECKING:  # the guide brings JAX; the plain search starts without it
    from rllock.search.guide import Guide

# How often a running search reports its progress, in seconds.
PROGRESS_EVERY = 0.5
DIVE_POOL = 64  # dive states kept for later restarts (`SearchConfig.dives`): the best, a bounded memory
DIVE_STREAM = 1  # the diving restarts' generator is seeded [seed, DIVE_STREAM], apart from the solver's


@dataclass(frozen=True)
class SearchConfig:
    samples_per_node: int = 512
    """Raw chunks sampled when a node is expanded."""
    children: int = 8
    """Distinct accepted chunks kept per node (which, and in what order they are tried: `remainder`,
    `child_order`)."""
    restart_base: int = 64
    """Node expansions per unit of the Luby restart schedule (at least)."""
    restart_per_piece: int = 4
    """The Luby unit is at least this many expansions per piece to place (`deep_restart_per_piece` in
    deep mode): a deep search needs hundreds of expansions only to walk down once with lookahead."""
    closed_share: float | None = None
    """Share of the raw chunks drawn by the closed proposal (`compiled_sampler`), which grows chunks
    that slide out along one direction, so that big pieces are removable; the rest grow uniformly from
    the frontier. None: by piece size n, 0 below `closed_from`, 1/2 up to `closed_only_from`, then 1.
    Measured (seed 0, one core): frontier growth alone finds nothing on desia-bunny K=10-30 (n >= 32)
    and is faster on 5^3-6^3 cubes (n = 9-10); in between, half of each did best (desia-bunny K=40/60,
    mario K=30, desia-dog K=40)."""
    closed_from: int = 12
    """The piece size n from which `closed_share=None` draws closed-proposal chunks."""
    closed_only_from: int = 32
    """The piece size n from which `closed_share=None` draws closed-proposal chunks only."""
    deep_from: int = 2
    """From this K on, the search runs in deep mode, which keeps the remaining volume compact: pieces
    fail late, when what remains of R has become thin strands that no piece can be cut from without
    cutting R apart. In deep mode a chunk may start at any R voxel that touches a placed piece (not only
    the previous piece: stragglers get picked up), frontier growth takes the thinner of two frontier
    voxels, a node's children are its accepted chunks that leave R most compact (`remainder`,
    `env.tightest_subset`), and restarts are longer. Measured first on desia-dog K=60 (seed 0, one
    core): the default search reached 55 of 59 pieces in 300 s; the smallest cuts, 55; with wide seeds,
    57; with thin growth too, 58 in 240 s; with longer restarts too, all 59 in 111 s. It was the mode
    from K = 30 on until it was measured at small K too (docs/benchmarks.md, "Deep mode at every K"):
    seconds to the first assembly, seeds 0-2, fell on every cell tried (cube6 K=25 2.7-31 s to
    0.3-1.1 s, cube4 K=9 none in 60 s to 1.5-3.2 s) and sofa K=19, which no search of the solver had
    solved, was solved in 37-149 s. So it is the default at every K; `deep_from` stays to compare."""
    deep_restart_per_piece: int = 16
    """`restart_per_piece` in deep mode."""
    remainder: Literal["surface", "cut"] | None = None
    """Deep mode's judgement of a child's remainder: "surface" keeps the accepted chunks after which the
    remaining volume's surface grows least (the chunk's cut to the rest, less its faces to placed pieces
    and the outside: a chunk that takes a strand or a corner away is preferred, since a strand left to
    the end is what no last piece can lock); "cut" those with the smallest cut alone. None: by removal
    mode, "surface" under straight removal (sofa K=19 median 5.7 s to the first assembly against 60 s
    unsolved, cube4 K=9 0.1 s against 3.3 s), "cut" under path removal (desia-bunny K=80, seeds 0-5,
    120 s: cut solved 4, surface 2). Measured side by side (docs/benchmarks.md, "The remainder's
    surface")."""
    child_order: Literal["count", "remainder"] | None = None
    """The order a node's children are tried in, under lookahead: "remainder", in deep mode the order of
    `remainder`'s judgement (the least growth first); "count", the most accepted continuations first
    (the only order until the commit after 24493fb). Either way children with no continuation are
    dropped. None: by removal mode, "remainder" under straight removal, "count" under path removal.
    Rollouts from a node's kept children (`scripts/chunk_study.py`) ordered 61.8% of their sibling pairs
    rightly by the remainder's surface and 39.1% by the count (174 pairs); in the search, seeds 0-4,
    60 s, desia-dog K=60 was solved on 5 seeds against 2 and sofa K=19's median fell from 4.3 to 1.8 s;
    desia-bunny K=80 path, seeds 0-5, 120 s, was solved on 2 seeds against 4 (docs/benchmarks.md,
    "Which chunks become children, and in what order they are tried")."""
    order_within: int = 64
    """`child_order` "remainder" orders the children of nodes with at most this many pieces left to
    place; above, the count orders them. On the Stanford bunny at resolution 30 with K = 300 the
    remainder's order at every node took 292 s against the count's 19 s (seed 0); with it in the last 16
    pieces only, desia-dog K=60 lost most of its gain (seeds 0-2: none, 54.7, 0.7 s against 2.9, 6.9,
    8.6 s); in the last 64, the bunny took 20.7 and 20.1 s (seeds 0, 1; the count 19.1 and 22.1 s)."""
    lookahead: bool = True
    """Expand children as soon as their parent is, and try first the child with the most accepted
    continuations (fail-first pruning: children with none are dropped before they are entered)."""
    guide_count_weight: float = 0.5
    """With a guide network: the weight of the lookahead's count of accepted continuations (as a share
    of the node's most) beside the network's value when children are ordered."""
    prune_below: float = 0.02
    """With a guide network: children whose value is below this are dropped (the network judges that
    the search below them places almost none of the pieces left), except the best of a node's."""
    abandon_below: float = 0.0
    """With a guide network: a node whose every child is valued below this is abandoned, the search
    backtracks at once (most nodes' children all win or all lose: the failure was set higher up)."""
    guide_orders: bool = False
    """With a guide network: its values (and the lookahead share, `guide_count_weight`) order and prune
    (`prune_below`) the children of every node within its horizon. Off by default: guides ordered
    siblings about as the search's own order does and did not beat the plain search that way; they
    judge whole remainders, which `dives` asks of them (docs/benchmarks.md)."""
    demote_by: float | None = None
    """With a guide network and `guide_orders` False: a node's children valued more than this below its
    best child's value are tried after the others, each part in the search's own order (the solver's
    judgement stays first; the network only puts off the children it judges clearly worse)."""
    dives: int = 4
    """With a guide network: each restart of the diving sequence (`dive_share`) dives this many times
    from the root (the restart's own DFS, each dive stopped at the first state `Guide.horizon` pieces
    before the end), and the restart goes on from the dive state the network values best among these
    and those earlier restarts left untaken; 1 never dives, as the solver does. With 4, a guide taught
    mario solved mario K=60 on 12 seeds of 18 in 300 s, the untrained network on 4 and the solver on 2
    of 9; two more trainings of the same command, 2 of 8 and 3 of 17 (docs/benchmarks.md, "mario K=60
    on 18 seeds", "Which search the actors run").
    Tasks with at most `Guide.horizon` + 1 pieces have no dive state: there the guided search is the
    solver's."""
    dive_share: float = 0.5
    """With a guide network: the restarts that dive are a second Luby sequence beside the solver's own,
    on a generator of their own, and one begins only while the expansions of that sequence (with its
    planned budget) stay within this share of the solver sequence's (`dive_allowance`), both counted
    since the start or the last assembly. The solver's restarts are the plain solver's, bit for bit, so
    what the solver finds early the guided search finds too, within 1 + `dive_share` times its
    expansions (and the last diving restart's); 0 never dives. Before, every restart from the second
    dived, which cost easy cells up to 14x (the beetle mesh; docs/benchmarks.md, "The guide beside the
    solver"). Shares 1.0 and 2.0 solved mario K=60 on 7 seeds of 16 within 150 s where 0.5 solved 5,
    but single seeds of cells the solver solves within a minute took up to 2.2x its time: 0.5 keeps the
    bound of 1.5x by construction ("How much of the search the dives get")."""
    dive_share_grows_after: int = 8
    """Restart units (`restart_unit`) of the solver sequence's expansions after which the share grows
    in proportion to them: the longer the plain search fails, the more the dives get (the hard cells the
    guide is for). 8 units are the solver's first 6 restarts; it found the easy cells (under 5 s:
    desia-dog K=60, the beetle mesh at 24 with K=61, mario K=58 on 5 seeds of 6) within 0.5-6.5 units,
    and fandisk at 24 with K=174 on seed 0 in about 80 (docs/benchmarks.md, "The guide beside the
    solver")."""
    backjump: float | None = None
    """With a guide network: when a subtree fails, the search backtracks past the step on its path where
    the expected shortfall ((1 - value) x pieces left, in pieces) grew most, if it grew by at least this
    many pieces there (the failure was set at that step); None backtracks one step."""

    def values_children(self) -> bool:
        """Whether a guide's values of a node's children are used (to order, demote, abandon or backjump):
        with `guide_orders` False and none of the others, only the dive states are valued."""
        used = (self.demote_by, self.backjump)
        return self.guide_orders or self.abandon_below > 0 or any(u is not None for u in used)

    def share_for(self, task: Task) -> float:
        """The share of closed-proposal chunks for `task`."""
        if self.closed_share is not None:
            return self.closed_share
        n = task.piece_size
        return 1.0 if n >= self.closed_only_from else 0.5 if n >= self.closed_from else 0.0

    def deep(self, task: Task) -> bool:
        return task.pieces >= self.deep_from

    def by_remainder(self, task: Task, left: int) -> bool:
        """Whether a node with `left` pieces left to place tries its children in the order of the
        remainder's judgement (`child_order`, `order_within`): only in deep mode, where
        `env.tightest_subset` hands them over in that order."""
        return self.deep(task) and left <= self.order_within and _chosen(self.child_order, "remainder", task)

    def surface(self, task: Task) -> bool:
        """Whether deep mode keeps the children that grow the remainder's surface least (`remainder`)."""
        return _chosen(self.remainder, "surface", task)

    def restart_unit(self, task: Task, placed: int) -> int:
        """Node expansions per unit of the Luby schedule for a search of `task` to `placed` pieces."""
        per_piece = self.deep_restart_per_piece if self.deep(task) else self.restart_per_piece
        return max(self.restart_base, per_piece * placed)


def _chosen(choice: str | None, wanted: str, task: Task) -> bool:
    """Whether `choice` is `wanted`; None chooses it under straight removal only, where it was measured
    better (under path removal the former search is kept)."""
    return task.removal == "straight" if choice is None else choice == wanted


@dataclass(frozen=True)
class Found:
    labels: np.ndarray  # int grid [x, y, z], 1..K
    seconds: float  # time since the previous assembly (or the start)
    expansions: int  # node expansions since the previous assembly
    seed: int  # the seed of the search that found it (its run with that seed finds it again)


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


def luby(i: int) -> int:
    """The i-th term (1-based) of the Luby sequence."""
    k = 1
    while (1 << k) - 1 < i:
        k += 1
    if i == (1 << k) - 1:
        return 1 << (k - 1)
    return luby(i - (1 << (k - 1)) + 1)


def _never() -> bool:
    return False


Record = Callable[[State, float], None]
"""Takes each state the search leaves (its subtree done, its restart cut short, or on an assembly's path),
with its lookahead share (`Child.share`): where a guide network's training (`actors.guide_actor`) picks
the states it labels."""


class Child(NamedTuple):
    """A node's child as the search keeps it: the state, its own candidate chunks when the lookahead
    sampled them, and its lookahead share (its accepted continuations over the most among its
    siblings; 0 without lookahead)."""

    state: State
    grand: np.ndarray | None
    share: float
    value: float | None = None  # the guide's, when it judged this child


# A node's children are sampled on threads only when one sample takes at least this long: shorter ones
# cost about as much to hand over as to run (measured on 2 cores: 0.35 ms samples on a 4^3 cube ran 1.2x
# as fast on two threads, 1.4-2.7 ms ones on 581-5,456 voxels 1.5-1.7x).
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
        its count's cache line bounce between the cores, which cost a sample about 5% more CPU time."""
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
    progress) and orders them, under lookahead and with a guide when there is one."""

    task: Task
    rng: np.random.Generator
    config: SearchConfig
    target: int
    stats: SearchStats
    report: Callable[[SearchStats], None] | None
    guide: Guide | None
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
            if len(waiting) < pool.threads and self.guide is None:
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
            return self.guided([Child(k, None, 0.0) for k in kids])
        scored = []
        config, task = self.config, self.task
        by_remainder = config.by_remainder(task, task.pieces - 1 - state.placed)
        for i, (kid, (grand, count)) in enumerate(zip(kids, self.sample_all(kids, chunks))):
            if len(grand):
                scored.append((pop_rank(i, count, by_remainder), count, kid, grand))
        scored.sort(key=lambda t: t[0])
        most = max((count for _, count, _, _ in scored), default=1)
        children = [Child(kid, grand, count / most) for _, count, kid, grand in scored]
        return self.guided(children)

    def guided(self, children: list[Child]) -> list[Child]:
        """`children` judged by the guide (`_guided`) when there is one and they are within its horizon
        (`Guide.horizon`: the pieces left where it was trained)."""
        guide = self.guide
        if guide is None or not children or self.target - children[0].state.placed > guide.horizon:
            return children
        if not self.config.values_children():
            return children
        return _guided(self.task, children, guide, self.config)


def pop_rank(index: int, count: int, by_remainder: bool) -> tuple[int, int]:
    """Where the child made by a node's `index`-th chunk, with `count` accepted continuations, goes in
    its node's pop order (the greatest is tried first): in the remainder's order the first chunk first
    (in deep mode the chunks come best first by its judgement, `tightest_subset`), else the most
    continuations first, the last such of equal counts."""
    return (-index if by_remainder else count, index)


def _dfs(
    task: Task,
    rng: np.random.Generator,
    config: SearchConfig,
    budget: int,
    deadline: float,
    target: int,
    stats: SearchStats,
    stop: Callable[[], bool] = _never,
    report: Callable[[SearchStats], None] | None = None,
    guide: Guide | None = None,
    record: Record | None = None,
    start: State | None = None,
    pool: SamplingPool | None = None,
):
    """One restart: DFS from the root (or `start`) for at most `budget` expansions until a state with
    `target` placed pieces, the deadline, or `stop()`. Returns (that state or None, expansions used); `stats`
    counts the expansions and keeps the deepest state, and `report(stats)` is called every
    PROGRESS_EVERY seconds. A `guide` may judge the children (`_guided`: all children of a node in one
    call; `SearchConfig.guide_orders` and what else asks for values); `record` takes every state the
    search leaves (`Record`)."""
    nodes = _Expander(task, rng, config, target, stats, report, guide, pool)
    root = initial_state(task) if start is None else start
    stack = [nodes.children_of(root, nodes.sample(root)[0])]
    path = [Child(root, None, 1.0)]  # the child each stack level holds the children of
    while stack:
        if nodes.expansions >= budget or time.monotonic() > deadline or stop():
            _left(path, record)
            return None, nodes.expansions
        if not stack[-1]:
            keep = _backjump(path, config.backjump, target)  # one step back unless the guide's values say
            while len(path) > keep:
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


def _backjump(path: list[Child], least: float | None, target: int) -> int:
    """How many levels of `path` stay when the subtree of its last child failed: all but that child, or
    (with `least` pieces) fewer, up to the child where the expected shortfall grew most."""
    keep = len(path) - 1
    if least is None:
        return keep
    best = least
    for i in range(1, len(path)):
        a, b = path[i - 1], path[i]
        if a.value is None or b.value is None:
            continue
        grew = (1 - b.value) * (target - b.state.placed) - (1 - a.value) * (target - a.state.placed)
        if grew >= best:
            best, keep = grew, i
    return keep


def _guided(task: Task, children: list[Child], guide: Guide, config: SearchConfig) -> list[Child]:
    """`children` in pop order by the guide's values plus
    `config.guide_count_weight` times their lookahead share, best last, without those valued below
    `config.prune_below` (never all, unless every one is valued below `config.abandon_below`). Each
    carries its value (for `_backjump`); with `config.guide_orders` False they keep their order (less
    those `config.demote_by` puts off) and none is pruned."""
    values = guide.values(task, [c.state for c in children], [c.share for c in children])
    if values.max() < config.abandon_below:
        return []
    children = [c._replace(value=float(v)) for c, v in zip(children, values)]
    if not config.guide_orders:
        if config.demote_by is None:
            return children
        worse = values < values.max() - config.demote_by
        return [c for c, w in zip(children, worse) if w] + [c for c, w in zip(children, worse) if not w]
    score = [values[i] + config.guide_count_weight * c.share for i, c in enumerate(children)]
    order = sorted(range(len(children)), key=lambda i: (score[i], i))
    kept = [children[i] for i in order if values[i] >= config.prune_below]
    return kept or [children[order[-1]]]  # never all: the best child is tried whatever its value


def search(
    task: Task,
    *,
    seed: int,
    time_limit: float,
    config: SearchConfig = SearchConfig(),
    stats: SearchStats | None = None,
    stop: Callable[[], bool] = _never,
    report: Callable[[SearchStats], None] | None = None,
    guide: Guide | None = None,
    record: Record | None = None,
    threads: int = 1,
    pool: SamplingPool | None = None,
) -> Generator[Found, None, None]:
    """Yield distinct valid assemblies (checked by the compiled checkers; the caller verifies before
    writing) until the time limit or `stop()`. Same seed, same sequence. `stats`, when given, is kept up
    to date (and passed to `report` every PROGRESS_EVERY seconds). A `guide` network picks where
    restarts begin (`SearchConfig.dives`) and, as configured, judges the children (`_dfs`); `record`
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
    kept: list[tuple[float, State]] = []  # dive states not yet taken, with their values (`_best_dive`)
    solver = _Sequence(np.random.default_rng(seed))
    diver = _Sequence(np.random.default_rng([seed, DIVE_STREAM]))
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
            _best_dive(task, run.rng, config, budget, deadline, stats, stop, report, guide, pool, kept)
            if diving
            else (None, 0)
        )
        state, expansions = _dfs(
            task,
            run.rng,
            config,
            budget,
            deadline,
            task.pieces - 1,
            stats,
            stop,
            report,
            guide,
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


@dataclass
class _Sequence:
    """One Luby sequence of restarts (`SearchConfig.dive_share`): its generator, its restarts and the
    expansions they used since the start or the last assembly, and since the start, its diving
    restarts and their dives' expansions."""

    rng: np.random.Generator
    restarts: int = 0
    used: int = 0
    ran: int = 0
    dived: int = 0

    def planned(self, unit: int, least: int) -> float:
        """The expansions its next restart is planned to take: its Luby budget, and its dives as many
        as they took on average so far, or `least` before any (one expansion a piece: a dive is a
        DFS to its depth). On a mesh of 3,825 voxels with K=255 one restart's dives took about 1.8
        restart units where its budget was 1 (docs/benchmarks.md, "The guide beside the solver")."""
        return unit * luby(self.restarts + 1) + (self.dived / self.ran if self.ran else least)


def dive_allowance(config: SearchConfig, unit: int, used: int) -> float:
    """The expansions the diving restarts may have used beside `used` of the solver's restarts
    (`SearchConfig.dive_share`): the share of them, and past `dive_share_grows_after` units, a share
    grown in proportion to them."""
    return config.dive_share * used * max(1.0, used / (config.dive_share_grows_after * unit))


def dive_depth(task: Task, guide: Guide) -> int:
    """The pieces placed at a dive state (`SearchConfig.dives`): `guide.horizon` pieces before the end.
    Below 1, `task` has no dive state and a guided search is the solver's."""
    return task.pieces - 1 - guide.horizon


def _best_dive(
    task: Task,
    rng: np.random.Generator,
    config: SearchConfig,
    budget: int,
    deadline: float,
    stats: SearchStats,
    stop: Callable[[], bool],
    report: Callable[[SearchStats], None] | None,
    guide: Guide | None,
    pool: SamplingPool | None,
    kept: list[tuple[float, State]],
) -> tuple[State | None, int]:
    """Where a restart begins (`SearchConfig.dives`): `config.dives` dives from the root to `guide.horizon`
    pieces before the end go into `kept` (the dive states of earlier restarts not yet taken, with their
    values, best last, at most `DIVE_POOL`), and the best of it is taken; with the expansions the dives
    took. (None, 0), the root, without a guide or with one dive."""
    if guide is None or config.dives <= 1:
        return None, 0
    depth = dive_depth(task, guide)
    if depth < 1:
        return None, 0
    reached, used = [], 0
    for _ in range(config.dives):
        state, spent = _dfs(task, rng, config, budget, deadline, depth, stats, stop, report, pool=pool)
        used += spent
        if state is not None:
            reached.append(state)
    # One share for all: a dive state's lookahead share among its own siblings says nothing across dives.
    values = guide.values(task, reached, [1.0] * len(reached))
    kept += zip(values.tolist(), reached)
    kept.sort(key=lambda t: t[0])  # stable: of equal values, the newest last
    del kept[: max(0, len(kept) - DIVE_POOL)]
    return (kept.pop()[1] if kept else None), used


def reach_depth(
    task: Task, placed: int, *, seed: int, time_limit: float, config: SearchConfig = SearchConfig()
) -> State | None:
    """A valid state with `placed` pieces (a seeded mid-episode state), or None within the time limit."""
    deadline = time.monotonic() + time_limit
    return _restarts(task, np.random.default_rng(seed), config, placed, None, deadline, None)


def _restarts(
    task: Task,
    rng: np.random.Generator,
    config: SearchConfig,
    target: int,
    start: State | None,
    deadline: float,
    expansions: int | None,
    stats: SearchStats | None = None,
) -> State | None:
    """Restarts of `_dfs` from `start` (or the root) with Luby budgets until a state with `target`
    pieces placed (returned), the deadline or `expansions` node expansions in all, when given (None).
    `stats`, when given, counts over all the restarts (its deepest state among them)."""
    used, restart = 0, 0
    left = target - (0 if start is None else start.placed)
    stats = SearchStats() if stats is None else stats
    while (expansions is None or used < expansions) and time.monotonic() < deadline:
        restart += 1
        budget = config.restart_unit(task, left) * luby(restart)
        if expansions is not None:
            budget = min(budget, expansions - used)
        state, spent = _dfs(task, rng, config, budget, deadline, target, stats, start=start)
        if state is not None:
            return state
        used += spent
    return None


def _left(states: list[Child], record: Record | None) -> None:
    """The search leaves `states` (a subtree done, a restart cut short, or an assembly's path)."""
    if record is not None:
        for c in states:
            record(c.state, c.share)


def expand(task: Task, state: State, *, seed: int, config: SearchConfig = SearchConfig()) -> list[Child]:
    """The children of `state` as the search makes them (sampled, the lookahead's count kept as their
    share, those with no continuation dropped), in pop order: best last."""
    nodes = _Expander(task, np.random.default_rng(seed), config, task.pieces - 1, SearchStats(), None, None)
    return nodes.children_of(state, nodes.sample(state)[0])


def rollout_reach(
    task: Task, state: State, *, seed: int, expansions: int, config: SearchConfig = SearchConfig()
) -> float:
    """A rollout that judges the remainder `state` leaves: the search restarted from it (Luby budgets,
    `expansions` node expansions in all). The share of the pieces left below `state` that it placed at
    best, 1.0 when it reached an assembly: where every rollout fails (a hard task) it still tells a
    remainder that ends one piece short from one that ends ten short."""
    target = task.pieces - 1
    if state.placed == target:
        return 1.0
    stats = SearchStats()
    rng = np.random.default_rng(seed)
    if _restarts(task, rng, config, target, state, float("inf"), expansions, stats) is not None:
        return 1.0
    return (max(stats.placed, state.placed) - state.placed) / (target - state.placed)


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
