"""Search actors for the guide network (`rllock train-guide`). Each call draws a curriculum task and runs
the search solver on it with the latest guide weights (every other search without a guide, so that the
run shows what the guide changes), keeping a few of the states it left (`solver.Record`), `min_left`
to `max_left` pieces before the end (a reservoir sample). Each kept state's children, as the search
makes them, are then labelled by rollouts: the share of `rollouts` plain searches from the child that
reach an assembly.
The encoded children, their labels and which are siblings go to the replay buffer actor.

Why rollouts: how deep the search happened to go below a state is mostly the search's luck, and a
network trained on it orders siblings no better than chance; a child's rollouts mostly agree (all win
or all lose), so its label is a property of the remainder it leaves.
"""

from __future__ import annotations

import os
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import ray

from rllock.config import GuideTrainConfig
from rllock.core.env import State, Task
from rllock.process import peak_rss_mb
from rllock.search.base import BufferCounts, derive_seed
from rllock.search.curriculum import draw_task, named_tasks
from rllock.search.dfs import SearchStats, expand
from rllock.search.guide import GLOBALS, Guide, channels, encode
from rllock.search.restarts import rollout_reach
from rllock.search.solver import search

# States kept per probe wanted: most states a failing search leaves are dead ends (no child to label),
# and without spares its probes would mostly be those, so that the searches that fail, where labels
# matter most, would give none.
PROBE_CANDIDATES = 8


@dataclass(frozen=True)
class SearchReport:
    """One search of the curriculum, as the driver counts it."""

    task: str  # "shape K=.. removal"
    cell: str  # the task's label in --cells ("" for a drawn task)
    guided: bool
    solved: bool
    placed: int  # the most pieces placed
    pieces: int  # K
    states: int  # labelled children pushed
    winning: float  # their mean label
    seconds: float
    version: int
    pid: int
    peak_rss_mb: float
    buffer: BufferCounts | None = None


@dataclass
class SearchTotals:
    """What the searches have done in all, and where `--edge` has moved each cell's K, as every
    checkpoint keeps it (`rllock.orchestration.recorder.Counters`): a resumed run goes on from there."""

    searches: int = 0
    solved: int = 0
    guided: int = 0
    guided_solved: int = 0
    states: int = 0  # labelled states pushed into the replay buffer
    edge: dict[str, int] = field(default_factory=dict)  # `--edge`: each cell's K now, by its label

    def add(self, report: SearchReport) -> None:
        self.searches += 1
        self.solved += report.solved
        self.guided += report.guided
        self.guided_solved += report.guided and report.solved
        self.states += report.states

    @property
    def produced(self) -> int:
        """What the replay ratio divides by."""
        return self.states


class Probes:
    """A uniform sample of at most `size` of the states a search left with `low` to `high` pieces to
    place (reservoir sampling: memory bounded whatever the search's length)."""

    def __init__(self, task: Task, size: int, low: int, high: int, rng: np.random.Generator):
        self.task, self.size, self.low, self.high, self.rng = task, size, low, high, rng
        self.kept: list[State] = []
        self.seen = 0

    def __call__(self, state: State, share: float) -> None:
        del share
        left = self.task.pieces - 1 - state.placed
        if not self.low <= left <= self.high:
            return
        self.seen += 1
        if len(self.kept) < self.size:
            self.kept.append(state)
        else:
            at = int(self.rng.integers(self.seen))
            if at < self.size:
                self.kept[at] = state


@dataclass(frozen=True)
class Labelled:
    """Encoded children with their rollout labels: the share of rollouts that reached an assembly, and
    what each rollout reached (`restarts.rollout_reach`: 1.0 an assembly)."""

    window: np.ndarray  # int8 [B, W, W, W, channels]
    features: np.ndarray  # float32 [B, GLOBALS]
    reach: np.ndarray  # float32 [B, rollouts]
    group: np.ndarray  # int64 [B]: the parent's number (siblings share it)

    @property
    def target(self) -> np.ndarray:
        """float32 [B]: the share of each child's rollouts that reached an assembly."""
        return (self.reach == 1.0).mean(axis=1, dtype=np.float32)


def label_children(task: Task, parents: list[State], config: GuideTrainConfig, seed: int) -> Labelled:
    """The children (`dfs.expand`) of the first `config.probes` of `parents` that have any, each
    labelled by the share of `config.rollouts` plain searches from it that reach an assembly."""
    w = config.guide.window
    depth = channels(config.guide)
    windows, features, reach = [np.zeros((0, w, w, w, depth), np.int8)], [np.zeros((0, GLOBALS))], []
    group: list[int] = []
    for p, parent in enumerate(parents):
        if len(set(group)) == config.probes:
            break
        children = expand(task, parent, seed=derive_seed(seed, p))
        if not children:
            continue
        e = encode(task, [c.state for c in children], [c.share for c in children], config.guide)
        windows.append(e.window)
        features.append(e.features)
        group += [p] * len(children)
        for c, child in enumerate(children):
            reach.append([
                rollout_reach(
                    task, child.state, seed=derive_seed(seed, p, c, r), expansions=config.rollout_expansions
                )
                for r in range(config.rollouts)
            ])  # fmt: skip
    return Labelled(
        np.concatenate(windows),
        np.concatenate(features).astype(np.float32),
        np.asarray(reach, np.float32).reshape(-1, config.rollouts),
        np.asarray(group, np.int64),
    )


def value_target(labelled: Labelled, label: str) -> np.ndarray:
    """The children's value targets under `GuideTrainConfig.label`: the share of rollouts that won, or
    the mean share of the pieces left they placed."""
    return labelled.target if label == "won" else labelled.reach.mean(axis=1)


def run_search(
    config: GuideTrainConfig,
    seed: int,
    number: int,
    guide: Guide | None,
    named: list[Task] | None = None,
    pieces: Mapping[str, int] | None = None,
) -> tuple[Labelled, bool, int, Task]:
    """Search number `number` of an actor seeded `seed` on a task of the curriculum (one of `named`, the
    tasks of `--cells`, when there are any, at the K `pieces` gives its label): (its labelled probes,
    solved, pieces placed, task)."""
    rng = np.random.default_rng([seed, number])
    task = draw_task(rng, config, named, pieces)
    probes = Probes(task, config.probes * PROBE_CANDIDATES, config.min_left, config.max_left, rng)
    stats = SearchStats()
    found = search(
        task,
        seed=derive_seed(seed, number),
        time_limit=config.search_seconds,
        stats=stats,
        guide=guide,
        record=probes,
    )
    solved = next(found, None) is not None
    return label_children(task, probes.kept, config, derive_seed(seed, number, 1)), solved, stats.placed, task


@ray.remote
class GuideActor:
    def __init__(self, seed: int, config: GuideTrainConfig):
        self.seed, self.config = seed, config
        self.named = named_tasks(config.cells) if config.cells else None
        self.params: Any = None
        self.version = -1
        self.searches = 0

    def run(
        self, weights: list, version: int, buffer: Any, pieces: Mapping[str, int] | None = None
    ) -> SearchReport:
        """`weights` is [ObjectRef of the guide's parameters]: fetched only for a new version; `pieces`
        the K of each cell of `--cells` now (`--edge`)."""
        if version != self.version:
            self.params, self.version = ray.get(weights[0]), version
        start = time.perf_counter()
        guided = version > 0 and self.searches % 2 == 0
        guide = (
            Guide(self.config.guide, self.params, f"version {version}", self.config.max_left)
            if guided
            else None
        )
        labelled, solved, placed, task = run_search(
            self.config, self.seed, self.searches, guide, self.named, pieces
        )
        self.searches += 1
        target = value_target(labelled, self.config.label)
        counts = ray.get(buffer.add.remote(labelled.window, labelled.features, target, labelled.group))
        return SearchReport(
            f"{task.shape_name} K={task.pieces} {task.removal}",
            task.shape_name if self.named else "",
            guided,
            solved,
            placed,
            task.pieces,
            len(labelled.target),
            float(target.mean()) if len(target) else 0.0,
            time.perf_counter() - start,
            version,
            os.getpid(),
            peak_rss_mb(),
            counts,
        )
