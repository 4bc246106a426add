"""The guided dives: with a guide network, a second sequence of restarts beside the solver's own begins
each restart from the dive state the network values best, within a share of the solver's expansions, so
that what the solver finds early the guided search finds too."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from rllock.core.env import State, Task
from rllock.search.dfs import SamplingPool, SearchStats, dfs
from rllock.search.restarts import luby
from rllock.search.search_config import SearchConfig

if TYPE_CHECKING:  # the guide brings JAX; the plain search starts without it
    from rllock.search.guide import Guide

DIVE_POOL = 64  # dive states kept for later restarts (`SearchConfig.dives`): the best, a bounded memory
DIVE_STREAM = 1  # the diving restarts' generator is seeded [seed, DIVE_STREAM], apart from the solver's


@dataclass
class RestartSequence:
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
        DFS to its depth; on large shapes dives can take more than the restart's own budget)."""
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


def best_dive(
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
        state, spent = dfs(task, rng, config, budget, deadline, depth, stats, stop, report, pool=pool)
        used += spent
        if state is not None:
            reached.append(state)
    # One share for all: a dive state's lookahead share among its own siblings says nothing across dives.
    values = guide.values(task, reached, [1.0] * len(reached))
    kept += zip(values.tolist(), reached)
    kept.sort(key=lambda t: t[0])  # stable: of equal values, the newest last
    del kept[: max(0, len(kept) - DIVE_POOL)]
    return (kept.pop()[1] if kept else None), used
