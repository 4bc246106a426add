"""The environment as pure functions over explicit state (pgx style): a task, a state, candidates, a step.

A state A_i is int16 labels per voxel of the shape (0 = remaining volume R_i, j = piece Pj) and i, the
number of placed pieces. The first voxel of P1 is drawn uniformly from all voxels of R_0 (the paper
leaves this open); later pieces start next to the previous piece.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rllock.core import compiled_checkers as checkers
from rllock.core import compiled_sampler as sampler
from rllock.core.reference_checkers import REMOVAL_MODES
from rllock.core.shapes import load_shape, piece_size
from rllock.core.topology import Topology, build_topology
from rllock.errors import RLLockError


@dataclass(frozen=True, eq=False)
class Task:
    shape_name: str
    topology: Topology
    pieces: int  # K
    removal: str  # "straight" or "path"

    @property
    def size(self) -> int:
        """N, the shape's voxel count."""
        return self.topology.size

    @property
    def piece_size(self) -> int:
        """n = floor(N / K): the size of P1..P(K-1)."""
        return self.size // self.pieces

    @property
    def last_size(self) -> int:
        """The last piece's size, N - (K-1)n: from n to n + K - 1."""
        return self.size - (self.pieces - 1) * self.piece_size


def tight(size: int, pieces: int) -> bool:
    """Whether K = `pieces` on `size` voxels leaves the last piece under twice the others (N mod K < N // K):
    the one such K of each piece size n is N // n, the hardest of the K that give pieces of n voxels, as
    the last piece takes what the others leave (mario, N = 548: a last piece of 17 at K = 60, of 68 at
    K = 61, of 20 at K = 67 and of 12 at K = 68)."""
    return size % pieces < size // pieces


@dataclass(frozen=True, eq=False)
class State:
    labels: np.ndarray  # int16[N]
    placed: int  # i: pieces P1..Pi are placed


def make_task(
    shape: str | np.ndarray,
    pieces: int,
    removal: str = "straight",
    name: str | None = None,
    resolution: int | None = None,
) -> Task:
    if removal not in REMOVAL_MODES:
        raise RLLockError(f"unknown removal mode {removal!r}: use one of {', '.join(REMOVAL_MODES)}")
    grid = load_shape(shape, resolution) if isinstance(shape, str) else np.asarray(shape, dtype=bool)
    piece_size(int(grid.sum()), pieces)
    if pieces > np.iinfo(np.int16).max:
        raise RLLockError(f"K = {pieces} is too many pieces")
    label = name if name is not None else (shape if isinstance(shape, str) else "array")
    return Task(label, build_topology(grid), pieces, removal)


def compact_dtypes(task: Task) -> tuple[type[np.signedinteger], type[np.signedinteger]]:
    """(label dtype, voxel-number dtype): the smallest integers that hold K and N, for stored data."""
    label = np.int8 if task.pieces <= np.iinfo(np.int8).max else np.int16
    voxel = np.int16 if task.size <= np.iinfo(np.int16).max else np.int32
    return label, voxel


def initial_state(task: Task) -> State:
    return State(np.zeros(task.size, dtype=np.int16), 0)


def is_solved(task: Task, state: State) -> bool:
    return state.placed == task.pieces - 1


def apply_chunk(state: State, chunk: np.ndarray) -> State:
    labels = state.labels.copy()
    labels[chunk] = state.placed + 1
    return State(labels, state.placed + 1)


def assembly_key(labels: np.ndarray) -> bytes:
    """Identifies an assembly by its labels, to keep only distinct ones."""
    return labels.astype(np.int16).tobytes()


def final_labels(task: Task, state: State) -> np.ndarray:
    """Labels 1..K of a solved state: the remaining volume becomes piece K."""
    labels = state.labels.astype(np.int64)
    labels[labels == 0] = task.pieces
    return labels


CHECK_NAMES = {
    checkers.REMOVABLE: "removability",
    checkers.INTERLOCKING: "interlocking",
    checkers.CONNECTED: "connectivity of the rest",
}


def rejections(task: Task, state: State, *, seed: int, num_samples: int) -> tuple[int, dict[str, int]]:
    """Why the next piece is hard to place in `state`: (raw chunks that grew to n voxels, and for each
    check how many of them fail it) among `num_samples` samples. A chunk may fail several checks."""
    piece = state.placed + 1
    raw = sampler.sample_raw(task.topology.arrays, state.labels, piece, task.piece_size, num_samples, seed)
    if len(raw) == 0:
        return 0, {}
    passed = checkers.check_chunks(task.topology.arrays, state.labels, piece, raw, task.removal == "path")
    return len(raw), {name: int(((passed & bit) == 0).sum()) for bit, name in CHECK_NAMES.items()}


def sample_accepted(
    task: Task,
    state: State,
    *,
    seed: int,
    num_samples: int,
    closed_share: float = 0.0,
    thin: int = 0,
    wide_seeds: bool = False,
) -> np.ndarray:
    """All checker-accepted raw chunks among `num_samples` samples (duplicates kept): int32[k, n].
    A share `closed_share` of the raw chunks comes from the closed proposal; `thin` and `wide_seeds`
    as `compiled_sampler.sample_and_check_mixed` says."""
    accepted, _ = sampler.sample_and_check_mixed(
        task.topology.arrays,
        state.labels,
        state.placed + 1,
        task.piece_size,
        num_samples,
        task.removal == "path",
        seed,
        closed_share,
        thin,
        wide_seeds,
    )
    return accepted


def candidates(task: Task, state: State, *, seed: int, num_samples: int, max_candidates: int) -> np.ndarray:
    """A node's candidate actions: the first `max_candidates` distinct accepted chunks among at most
    `num_samples` raw samples (see `compiled_sampler`), each as sorted voxel numbers: int32[M, n].
    An empty result
    means a dead end."""
    found, _ = candidates_many(
        task,
        [state],
        np.array([seed]),
        num_samples=num_samples,
        max_candidates=max_candidates,
        parallel=False,
    )
    return found[0]


def candidates_many(
    task: Task,
    states: list[State],
    seeds: np.ndarray,
    *,
    num_samples: int,
    max_candidates: int,
    parallel: bool = True,
) -> tuple[list[np.ndarray], int]:
    """`candidates` for several states in one compiled call (with `parallel`, one numba thread per
    state; without, all on the calling thread); also the raw samples drawn in all."""
    labels = np.stack([s.labels for s in states])
    pieces = np.array([s.placed + 1 for s in states], np.int64)
    expand = sampler.candidates_many if parallel else sampler.candidates_serial
    out, found, drawn = expand(
        task.topology.arrays,
        labels,
        pieces,
        np.asarray(seeds, np.int64),
        task.piece_size,
        num_samples,
        max_candidates,
        task.removal == "path",
    )
    return [out[b, : found[b]] for b in range(len(states))], int(drawn.sum())


def distinct_subset(accepted: np.ndarray, count: int, seed: int) -> np.ndarray:
    """Up to `count` distinct chunks (as sorted voxel numbers) drawn uniformly from `accepted`."""
    unique = sampler.distinct_rows(accepted)
    return unique[np.random.default_rng(seed).permutation(len(unique))[:count]]


def tightest_subset(
    task: Task, state: State, accepted: np.ndarray, count: int, seed: int, surface: bool = True
) -> np.ndarray:
    """Up to `count` distinct chunks (as sorted voxel numbers) of `accepted`: those after which the
    remaining volume's surface grows least, or with `surface` False those with the smallest cut to the
    rest of it (`compiled_sampler.remainder_growth`); ties in random order."""
    unique = sampler.distinct_rows(accepted)
    growth = sampler.remainder_growth(task.topology.arrays[0], state.labels, unique, int(surface))
    order = np.lexsort((np.random.default_rng(seed).random(len(unique)), growth))
    return unique[order[:count]]
