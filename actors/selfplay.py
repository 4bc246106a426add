"""Self-play episodes with MCTS, as a plain class (`SelfPlayWorker`) and a Ray actor around it.

An actor plays `episodes` episodes in lockstep per call, with the weights version it was handed, pushes
them into the replay buffer actor (waiting for it: bounded in-flight data) and returns its statistics.
An actor with T cores splits its episodes into T lockstep groups searched in T threads
(`rllock.search.mcts.play_groups`), so that one group's sampler runs while another's network does; a lockstep
worker instead runs one large group with the sampler spread over numba's threads. Thread counts (XLA
runs the small network on one thread per group, which is fastest here) are set through the environment
of the actor's process (`actor_env`), so that actors never oversubscribe the cores they were given.
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import jax
import numpy as np
import ray

from rllock.config import MCTSConfig, NetConfig
from rllock.core.env import Task
from rllock.process import peak_rss_mb
from rllock.search.base import BufferCounts, Episode, Player, TimeSplit, derive_seed
from rllock.search.mcts import play_groups
from rllock.search.methods import players, space
from rllock.search.workload import Workload


def actor_env(threads: int, *, gpu: bool = False) -> dict[str, str]:
    """Environment variables of an actor process that may use `threads` cores (and a GPU, if `gpu`)."""
    env = {
        "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false",
        "NUMBA_NUM_THREADS": str(threads),
        "OMP_NUM_THREADS": "1",
    }
    if gpu:  # the learner in the driver shares the GPU (the CLI caps it at half its memory)
        env["XLA_PYTHON_CLIENT_MEM_FRACTION"] = "0.4"
    else:
        env["JAX_PLATFORMS"] = "cpu"
    return env


@dataclass(frozen=True)
class PlaySpec:
    """What a self-play worker plays: `episodes` episodes per batch of a task the workload draws, in
    `groups` lockstep groups, with this network and search; `method` (`rllock.config.METHODS`) says what
    an action is. The episodes come as the workload stores them."""

    workload: Workload
    net: NetConfig
    mcts: MCTSConfig
    method: str
    episodes: int
    groups: int = 1


@dataclass(frozen=True)
class PlayStats:
    episodes: int
    successes: int
    decisions: int
    simulations: int
    version: int
    pid: int  # the actor's process, to notice restarts
    node: str  # the Ray node it ran on, to say where actors run and notice moves
    peak_rss_mb: float
    seconds: float
    times: TimeSplit
    group: int = -1  # multi-task runs: the task group the batch drew
    pieces: int = 0  # the batch's K
    canvas: int = 0  # the canvas side the batch was played on
    buffer: BufferCounts | None = None  # the replay buffer's counts once it took the batch


@dataclass
class PlayTotals:
    """What self-play has played in all, as every checkpoint keeps it
    (`rllock.orchestration.recorder.Counters`): a resumed run goes on counting, and seeds its new actors past
    the episodes already played."""

    episodes: int = 0
    successes: int = 0
    simulations: int = 0
    transitions: int = 0  # pushed into the replay buffer, as it counted them at the last batch

    def add(self, stats: PlayStats) -> None:
        self.episodes += stats.episodes
        self.successes += stats.successes
        self.simulations += stats.simulations
        if stats.buffer is not None:
            self.transitions = stats.buffer.added

    @property
    def produced(self) -> int:
        """What the replay ratio divides by."""
        return self.transitions


def evaluate(
    searchers: Sequence[Player],
    params,
    task: Task,
    key: jax.Array,
    *,
    seed: int,
    times: TimeSplit | None = None,
) -> tuple[list[Episode], float]:
    """One batch of episodes (a lockstep group per searcher) and the seconds it took."""
    start = time.perf_counter()
    episodes = play_groups(searchers, params, task, key, seed=seed, times=times)
    return episodes, time.perf_counter() - start


class SelfPlayWorker:
    """Plays batches as `spec` says, with the weights it was last given."""

    def __init__(self, spec: PlaySpec, seed: int):
        self.spec = spec
        # PPO runs no search: its decisions cost one network call each, not simulations.
        self.simulations_per_decision = 0 if spec.method == "ppo" else spec.mcts.simulations
        # Compiled searches by action shape (M, n) and canvas: a multi-task run meets a few piece sizes
        # again and again, and compiling costs seconds.
        self.compiled: dict[tuple[tuple[int, int], int], Sequence[Player]] = {}
        self.key = jax.random.PRNGKey(seed)
        self.seed = seed
        self.params: dict | None = None
        self.version = -1
        self.batches = 0

    def set_weights(self, params, version: int) -> None:
        self.params, self.version = params, version

    def searchers(self, task: Task, canvas: int) -> Sequence[Player]:
        spec = self.spec
        key = (space(spec.method).action_shape(task, spec.mcts), canvas)
        if key not in self.compiled:
            net = replace(spec.net, canvas=canvas)
            self.compiled[key] = players(spec.method, net, spec.mcts, task, spec.episodes, spec.groups)
        return self.compiled[key]

    def play(self) -> tuple[list[Episode], PlayStats]:
        assert self.params is not None, "set_weights first"
        self.key, sub = jax.random.split(self.key)
        times = TimeSplit()
        seed = derive_seed(self.seed, self.batches)
        draw = self.spec.workload.draw(np.random.default_rng([seed, 7]))  # not the store's stream
        task = draw.task
        searchers = self.searchers(task, draw.canvas)
        episodes, seconds = evaluate(searchers, self.params, task, sub, seed=seed, times=times)
        episodes = self.spec.workload.stored(draw, episodes)
        self.batches += 1
        decisions = sum(len(e.z) for e in episodes)  # finished rows of the lockstep batch not counted
        stats = PlayStats(
            len(episodes),
            sum(e.success for e in episodes),
            decisions,
            decisions * self.simulations_per_decision,
            self.version,
            os.getpid(),
            ray.get_runtime_context().get_node_id() if ray.is_initialized() else "",
            peak_rss_mb(),
            seconds,
            times,
            draw.group,
            task.pieces,
            draw.canvas,
        )
        return episodes, stats


@ray.remote
class SelfPlayActor:
    """Plays batches with the latest published weights and pushes them into the replay buffer. Its
    constructor takes only the seed: what it plays comes with every call (`run`), so that a process Ray
    restarts needs nothing kept from the first one's construction."""

    def __init__(self, seed: int):
        self.seed = seed
        self.worker: SelfPlayWorker | None = None
        self.buffer: Any = None  # the replay buffer actor's handle (Ray types its methods as Never)

    def where(self) -> tuple[int, str]:
        """(this process, its Ray node)."""
        return os.getpid(), ray.get_runtime_context().get_node_id()

    def run(self, setup: list, weights: list, version: int) -> PlayStats:
        """`setup` is [ObjectRef of (PlaySpec, replay buffer handle)] and `weights` [ObjectRef of the
        parameters]: lists, so that Ray fetches them only when this process lacks them (its first call,
        or a new weights version)."""
        if self.worker is None:
            spec, self.buffer = ray.get(setup[0])
            self.worker = SelfPlayWorker(spec, self.seed)
        if version != self.worker.version:
            self.worker.set_weights(ray.get(weights[0]), version)
        episodes, stats = self.worker.play()
        # Waits for the buffer: bounded in-flight data. Its counts come back with the statistics, so that
        # the driver need not ask the buffer for them.
        counts = ray.get(self.buffer.add_many.remote(episodes, stats.pieces, stats.canvas))
        return replace(stats, buffer=counts)
