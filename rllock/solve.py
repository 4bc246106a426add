"""The search solver: randomized depth-first search with backtracking and restarts over sampled chunks.

No learning. Each node samples raw chunks and keeps up to `children` distinct accepted ones in random
order; the search backtracks when a node's children are exhausted. Search trees for this problem are
heavy-tailed (one bad early piece can doom a whole subtree), so the search restarts from the root after
a budget of node expansions that follows the Luby sequence (1, 1, 2, 1, 1, 2, 4, ...) times
`restart_base`: short runs most of the time, occasionally long ones, which is within a log factor of
the best fixed budget without knowing it.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from rllock.env import State, Task, apply_chunk, candidates, final_labels, initial_state, is_solved


@dataclass(frozen=True)
class SearchConfig:
    samples_per_node: int = 512
    """Raw chunks sampled when a node is expanded."""
    children: int = 8
    """Distinct accepted chunks kept per node (tried in random order)."""
    restart_base: int = 64
    """Node expansions per unit of the Luby restart schedule."""


@dataclass(frozen=True)
class Found:
    labels: np.ndarray  # int grid [x, y, z], 1..K
    seconds: float  # time since the previous assembly (or the start)
    expansions: int  # node expansions since the previous assembly


def luby(i: int) -> int:
    """The i-th term (1-based) of the Luby sequence."""
    k = 1
    while (1 << k) - 1 < i:
        k += 1
    if i == (1 << k) - 1:
        return 1 << (k - 1)
    return luby(i - (1 << (k - 1)) + 1)


def _dfs(task: Task, rng: np.random.Generator, config: SearchConfig, budget: int, deadline: float):
    """One restart: DFS from the root for at most `budget` expansions. Returns (solved state or None,
    expansions used)."""
    expansions = 0

    def expand(state: State) -> list[np.ndarray]:
        nonlocal expansions
        expansions += 1
        seed = int(rng.integers(1 << 31))
        return list(candidates(task, state, seed=seed, num_samples=config.samples_per_node,
                               max_candidates=config.children))

    root = initial_state(task)
    stack: list[tuple[State, list[np.ndarray]]] = [(root, expand(root))]
    while stack:
        if expansions >= budget or time.monotonic() > deadline:
            return None, expansions
        state, children = stack[-1]
        if not children:
            stack.pop()
            continue
        child = apply_chunk(state, children.pop())
        if is_solved(task, child):
            return child, expansions
        stack.append((child, expand(child)))
    return None, expansions


def search(task: Task, *, seed: int, time_limit: float, config: SearchConfig = SearchConfig()) -> Iterator[Found]:
    """Yield distinct valid assemblies (checked by the compiled checkers; the caller verifies before
    writing) until the time limit. Same seed, same sequence."""
    rng = np.random.default_rng(seed)
    start = time.monotonic()
    deadline = start + time_limit
    seen: set[bytes] = set()
    last, used, restart = start, 0, 0
    while time.monotonic() < deadline:
        restart += 1
        state, expansions = _dfs(task, rng, config, config.restart_base * luby(restart), deadline)
        used += expansions
        if state is None:
            continue
        labels = final_labels(task, state)
        key = labels.astype(np.int16).tobytes()
        if key in seen:
            continue
        seen.add(key)
        now = time.monotonic()
        yield Found(task.topology.to_grid(labels), now - last, used)
        last, used, restart = now, 0, 0
