"""Self-play episodes with MCTS, as a plain class (`SelfPlayWorker`) and a Ray actor around it."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

import jax
import numpy as np
import ray

from rllock.env import Task, make_task, peak_rss_mb
from rllock.mcts import Episode, MCTSConfig, Searcher, play
from rllock.network import NetConfig, PolicyValueNet

# One XLA and one numba thread per actor: actors are one per core, so more threads only contend.
ACTOR_ENV = {
    "JAX_PLATFORMS": "cpu",
    "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false",
    "NUMBA_NUM_THREADS": "1",
    "OMP_NUM_THREADS": "1",
}


@dataclass(frozen=True)
class TaskSpec:
    """A task as plain data, so that it can travel to other processes."""

    grid: np.ndarray
    pieces: int
    removal: str
    name: str

    @staticmethod
    def of(task: Task) -> "TaskSpec":
        return TaskSpec(task.topology.grid, task.pieces, task.removal, task.shape_name)

    def make(self) -> Task:
        return make_task(self.grid, self.pieces, self.removal, name=self.name)


@dataclass(frozen=True)
class SelfPlayConfig:
    episodes_per_batch: int = 8
    """Episodes run in lockstep: each simulation evaluates all their leaves in one network call."""
    mcts: MCTSConfig = field(default_factory=MCTSConfig)
    net: NetConfig = field(default_factory=NetConfig)


@dataclass(frozen=True)
class PlayStats:
    episodes: int
    successes: int
    simulations: int
    version: int
    pid: int  # the actor's process, to notice restarts
    peak_rss_mb: float


def evaluate(searcher: Searcher, params, task: Task, key: jax.Array, *, batch: int, seed: int,
             canvas: int) -> tuple[list[Episode], float]:
    """One lockstep batch of episodes and the seconds it took."""
    start = time.perf_counter()
    episodes = play(searcher, params, task, key, batch=batch, seed=seed, canvas=canvas)
    return episodes, time.perf_counter() - start


class SelfPlayWorker:
    def __init__(self, spec: TaskSpec, config: SelfPlayConfig, seed: int):
        self.task = spec.make()
        self.config = config
        self.searcher = Searcher(PolicyValueNet(config.net), config.mcts, config.net.canvas,
                                 self.task.piece_size, config.episodes_per_batch)
        self.key = jax.random.PRNGKey(seed)
        self.seed = seed
        self.params = None
        self.version = -1
        self.batches = 0

    def set_weights(self, params, version: int) -> None:
        self.params, self.version = params, version

    def play(self) -> tuple[list[Episode], PlayStats]:
        assert self.params is not None, "set_weights first"
        self.key, sub = jax.random.split(self.key)
        batch = self.config.episodes_per_batch
        episodes, _ = evaluate(self.searcher, self.params, self.task, sub, batch=batch,
                               seed=self.seed * 1_000_003 + self.batches, canvas=self.config.net.canvas)
        self.batches += 1
        decisions = sum(len(e.z) for e in episodes)  # finished rows of the lockstep batch not counted
        stats = PlayStats(len(episodes), sum(e.success for e in episodes),
                          decisions * self.config.mcts.simulations, self.version, os.getpid(), peak_rss_mb())
        return episodes, stats


@ray.remote(num_cpus=1)
class SelfPlayActor:
    """Plays batches with the latest published weights and pushes them into the replay buffer."""

    def __init__(self, spec: TaskSpec, config: SelfPlayConfig, seed: int, buffer):
        self.worker = SelfPlayWorker(spec, config, seed)
        self.buffer = buffer

    def pid(self) -> int:
        return os.getpid()

    def run(self, weights: list, version: int) -> PlayStats:
        """`weights` is [ObjectRef] so that Ray does not fetch it unless the version changed."""
        if version != self.worker.version:
            self.worker.set_weights(ray.get(weights[0]), version)
        episodes, stats = self.worker.play()
        ray.get(self.buffer.add_many.remote(episodes))  # waits: bounded in-flight data
        return stats
