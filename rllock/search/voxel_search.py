"""RL-Lock_Action's search nodes: MCTS over voxel actions (`rllock.core.voxel_env`) in the same batched
search as RL-Lock (`rllock.search.mcts.Searcher`).

A node's candidate actions are its legal voxels, each as a one-voxel chunk, so the network scores them
with the same per-voxel logits, and episodes go through the same replay buffer and learner. The
encoding marks the growing piece where RL-Lock's marks the previous one (the piece new voxels must
touch): it is given `placed + 1` while a piece grows. The paper's baseline searches with 128
simulations per voxel decision, depth at most 32 and at most 16 actions considered.
"""

from __future__ import annotations

import time

import numpy as np

from rllock.config import MCTSConfig
from rllock.core.env import Task
from rllock.core.voxel_env import VoxelState, initial_voxel_state, legal_mask, step
from rllock.search.nodes import NodeStore


class VoxelStore(NodeStore):
    """RL-Lock_Action's actions: one voxel each; every legal voxel is a candidate (M = N)."""

    @staticmethod
    def action_shape(task: Task, config: MCTSConfig) -> tuple[int, int]:
        return task.size, 1

    def initial(self) -> VoxelState:
        return initial_voxel_state(self.task)

    def candidates(self, states: list) -> list[np.ndarray]:
        start = time.perf_counter()
        out = [np.flatnonzero(legal_mask(self.task, s)).astype(np.int32)[:, None] for s in states]
        self.times.sampling += time.perf_counter() - start
        return out

    def apply(self, state: VoxelState, action: np.ndarray) -> VoxelState:
        return step(self.task, state, int(action[0]))[0]

    def encoded_placed(self, state: VoxelState) -> int:
        return state.placed + (state.filled > 0)
