"""Random states and chunks for the equivalence tests."""

from __future__ import annotations

import numpy as np

from rllock import reference as ref
from rllock.env import State, Task, apply_chunk, candidates, initial_state


def voxel_labels(task: Task, state: State) -> dict[ref.Voxel, int]:
    return {tuple(int(c) for c in task.topology.coords[v]): int(state.labels[v]) for v in range(task.size)}


def parts_after(task: Task, state: State, chunk: np.ndarray) -> tuple[list[ref.Part], ref.Part]:
    """(P1..Pi, R_i) as coordinate sets once `chunk` becomes piece i."""
    coords = [tuple(int(c) for c in xyz) for xyz in task.topology.coords]
    labels = state.labels.copy()
    labels[chunk] = state.placed + 1
    parts = [frozenset(coords[v] for v in np.flatnonzero(labels == j)) for j in range(1, state.placed + 2)]
    return parts, frozenset(coords[v] for v in np.flatnonzero(labels == 0))


def raw_chunks(task: Task, state: State, rng: np.random.Generator, count: int) -> np.ndarray:
    """Unchecked chunks from the reference sampler, as voxel numbers: int32[k, n]."""
    labels = voxel_labels(task, state)
    out = []
    for _ in range(count):
        chunk = ref.sample_chunk(labels, state.placed + 1, task.piece_size, rng)
        if chunk is not None:
            out.append([int(task.topology.index[v]) for v in chunk])
    return np.array(out, dtype=np.int32).reshape(-1, task.piece_size)


def random_valid_states(task: Task, rng: np.random.Generator, episodes: int):
    """Every state along `episodes` random walks through accepted chunks (until a dead end)."""
    for _ in range(episodes):
        state = initial_state(task)
        while state.placed < task.pieces - 1:
            yield state
            cands = candidates(
                task, state, seed=int(rng.integers(1 << 30)), num_samples=512, max_candidates=8
            )
            if len(cands) == 0:
                break
            state = apply_chunk(state, cands[rng.integers(len(cands))])
