"""Search actors for the guide network (`rllock train-guide`): each call draws a curriculum task, runs the
search solver on it with the latest guide weights (every other search without a guide, so that the
data also shows what the plain search meets), and pushes the states the search finished, encoded, with
their value targets into the replay buffer actor."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import ray

from rllock.config import GuideTrainConfig
from rllock.core.env import State, Task
from rllock.process import peak_rss_mb
from rllock.search.base import BufferCounts, derive_seed
from rllock.search.curriculum import draw_task
from rllock.search.guide import CHANNELS, GLOBALS, Guide, encode
from rllock.search.solver import SearchStats, search


@dataclass(frozen=True)
class SearchReport:
    """One search of the curriculum, as the driver counts it."""

    task: str  # "shape K=.. removal"
    guided: bool
    solved: bool
    placed: int  # the most pieces placed
    pieces: int  # K
    states: int  # states recorded
    seconds: float
    version: int
    pid: int
    peak_rss_mb: float
    buffer: BufferCounts | None = None


class Recording:
    """The states a search finished, encoded as they come, with their targets."""

    def __init__(self, task: Task, window: int):
        self.task, self.window = task, window
        self.windows: list[np.ndarray] = []
        self.features: list[np.ndarray] = []
        self.targets: list[float] = []

    def __call__(self, state: State, target: float, share: float) -> None:
        e = encode(self.task, [state], [share], self.window)
        self.windows.append(e.window[0])
        self.features.append(e.features[0])
        self.targets.append(target)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        w = self.window
        if not self.targets:
            return np.zeros((0, w, w, w, CHANNELS), np.int8), np.zeros((0, GLOBALS), np.float32), np.zeros(0)
        return np.stack(self.windows), np.stack(self.features), np.asarray(self.targets, np.float32)


def run_search(
    config: GuideTrainConfig, seed: int, number: int, guide: Guide | None
) -> tuple[Recording, bool, int, Task]:
    """Search number `number` of an actor seeded `seed`: (its recording, solved, pieces placed, task)."""
    task = draw_task(np.random.default_rng([seed, number]), config)
    recording = Recording(task, config.guide.window)
    stats = SearchStats()
    found = search(
        task,
        seed=derive_seed(seed, number),
        time_limit=config.search_seconds,
        stats=stats,
        guide=guide,
        record=recording,
    )
    solved = next(found, None) is not None
    return recording, solved, stats.placed, task


@ray.remote
class GuideActor:
    def __init__(self, seed: int, config: GuideTrainConfig):
        self.seed, self.config = seed, config
        self.params: Any = None
        self.version = -1
        self.searches = 0

    def run(self, weights: list, version: int, buffer: Any) -> SearchReport:
        """`weights` is [ObjectRef of the guide's parameters]: fetched only for a new version."""
        if version != self.version:
            self.params, self.version = ray.get(weights[0]), version
        start = time.perf_counter()
        guided = version > 0 and self.searches % 2 == 0
        guide = Guide(self.config.guide, self.params, f"version {version}") if guided else None
        recording, solved, placed, task = run_search(self.config, self.seed, self.searches, guide)
        self.searches += 1
        counts = ray.get(buffer.add.remote(*recording.arrays()))
        return SearchReport(
            f"{task.shape_name} K={task.pieces} {task.removal}",
            guided,
            solved,
            placed,
            task.pieces,
            len(recording.targets),
            time.perf_counter() - start,
            version,
            os.getpid(),
            peak_rss_mb(),
            counts,
        )
