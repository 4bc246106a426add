"""The voxel-level MDP of the paper's section 3: one voxel per action, for the RL-Lock_Action and PPO
baselines. It sits beside the chunk environment (`rllock.core.env`) and uses the same checkers.

- The first voxel of piece P_i comes from the remaining voxels that face-touch P_(i-1) (any remaining
  voxel for P_1), each later one from the remaining voxels that face-touch the growing piece: the chunk
  sampler's rules, one draw at a time, so the pieces this MDP can build are the chunks it can sample.
- When a piece reaches n voxels, the three checkers run on it as a chunk. Accepted: reward 1/K, the
  chunk environment's normalised per-piece reward; the episode ends, solved, when K-1 pieces are placed
  (the rest is the last piece). Rejected: the episode ends, with reward 0. A piece that cannot grow (no
  legal voxel) also ends it.

A state's labels hold the growing piece's voxels with label `placed + 1` already.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rllock.core import compiled_checkers as checkers
from rllock.core.env import Task


@dataclass(frozen=True, eq=False)
class VoxelState:
    labels: np.ndarray  # int16[N]: 0 for R, j for piece Pj, placed + 1 for the growing piece
    placed: int  # pieces P1..Pi completed and accepted
    filled: int  # voxels of the growing piece P_(i+1) so far
    failed: bool = False  # a completed piece was rejected, or the piece could not grow


def initial_voxel_state(task: Task) -> VoxelState:
    return VoxelState(np.zeros(task.size, np.int16), 0, 0)


def is_solved(task: Task, state: VoxelState) -> bool:
    return state.placed == task.pieces - 1


def is_terminal(task: Task, state: VoxelState) -> bool:
    return state.failed or is_solved(task, state) or not legal_mask(task, state).any()


def legal_mask(task: Task, state: VoxelState) -> np.ndarray:
    """bool[N]: the voxels an action may assign to the growing piece."""
    if state.failed or is_solved(task, state):
        return np.zeros(task.size, bool)
    remaining = state.labels == 0
    if state.filled == 0 and state.placed == 0:
        return remaining
    target = state.placed + 1 if state.filled > 0 else state.placed
    nbr = task.topology.nbr
    touches = ((nbr >= 0) & (state.labels[nbr] == target)).any(axis=1)
    return remaining & touches


def step(task: Task, state: VoxelState, voxel: int) -> tuple[VoxelState, float]:
    """Assign `voxel` to the growing piece: (next state, reward). The action must be legal."""
    if not legal_mask(task, state)[voxel]:
        raise ValueError(f"voxel {voxel} is not a legal action in this state")
    piece = state.placed + 1
    labels = state.labels.copy()
    labels[voxel] = piece
    if state.filled + 1 < task.piece_size:
        return VoxelState(labels, state.placed, state.filled + 1), 0.0
    chunk = np.flatnonzero(labels == piece).astype(np.int32)
    if piece_accepted(task, state.labels, piece, chunk):
        return VoxelState(labels, piece, 0), 1.0 / task.pieces
    return VoxelState(labels, state.placed, state.filled + 1, failed=True), 0.0


def piece_accepted(task: Task, labels: np.ndarray, piece: int, chunk: np.ndarray) -> bool:
    """The chunk checkers on a completed piece: `labels` may hold the piece's voxels as label `piece`
    or as R; the checkers see them as R, as for a sampled chunk."""
    before = np.where(labels == piece, 0, labels).astype(np.int16)
    bits = checkers.check_chunks(task.topology.arrays, before, piece, chunk[None, :], task.removal == "path")
    return int(bits[0]) == checkers.ALL_CHECKS
