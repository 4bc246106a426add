"""Restarts: search trees for this problem are heavy-tailed (one bad early piece can doom a whole
subtree), so the search restarts from the root (or a given state) after a budget of node expansions that
follows the Luby sequence (1, 1, 2, 1, 1, 2, 4, ...) times a unit: short runs most of the time,
occasionally long ones, which is within a log factor of the best fixed budget without knowing it. Also
the searches built from restarts alone: a state at a given depth, and a rollout's reach."""

from __future__ import annotations

import time

import numpy as np

from rllock.core.env import State, Task
from rllock.search.dfs import SearchStats, dfs
from rllock.search.search_config import SearchConfig


def luby(i: int) -> int:
    """The i-th term (1-based) of the Luby sequence."""
    k = 1
    while (1 << k) - 1 < i:
        k += 1
    if i == (1 << k) - 1:
        return 1 << (k - 1)
    return luby(i - (1 << (k - 1)) + 1)


def reach_depth(
    task: Task, placed: int, *, seed: int, time_limit: float, config: SearchConfig = SearchConfig()
) -> State | None:
    """A valid state with `placed` pieces (a seeded mid-episode state), or None within the time limit."""
    deadline = time.monotonic() + time_limit
    return restart_until(task, np.random.default_rng(seed), config, placed, None, deadline, None)


def restart_until(
    task: Task,
    rng: np.random.Generator,
    config: SearchConfig,
    target: int,
    start: State | None,
    deadline: float,
    expansions: int | None,
    stats: SearchStats | None = None,
) -> State | None:
    """Restarts of `dfs` from `start` (or the root) with Luby budgets until a state with `target`
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
        state, spent = dfs(task, rng, config, budget, deadline, target, stats, start=start)
        if state is not None:
            return state
        used += spent
    return None


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
    if restart_until(task, rng, config, target, state, float("inf"), expansions, stats) is not None:
        return 1.0
    return (max(stats.placed, state.placed) - state.placed) / (target - state.placed)
