"""The training methods that search with MCTS: what one action is, and each method's own settings."""

from __future__ import annotations

import dataclasses

from rllock.config import METHODS, MCTSConfig
from rllock.errors import RLLockError
from rllock.mcts import ChunkStore, NodeStore
from rllock.voxel_search import VoxelStore

SPACES: dict[str, type[NodeStore]] = {"rl-lock": ChunkStore, "rl-lock-action": VoxelStore}
assert tuple(SPACES) == METHODS


def space(method: str) -> type[NodeStore]:
    try:
        return SPACES[method]
    except KeyError:
        raise RLLockError(f"unknown method {method!r}: use one of {', '.join(METHODS)}") from None


def with_method_defaults(method: str, mcts: MCTSConfig) -> MCTSConfig:
    """`mcts` with the method's own settings where it holds the general defaults: RL-Lock_Action
    searches with 128 simulations per voxel decision and depth at most 32 (the paper's section 5)."""
    if method != "rl-lock-action":
        return mcts
    general = MCTSConfig()
    return dataclasses.replace(
        mcts,
        simulations=128 if mcts.simulations == general.simulations else mcts.simulations,
        max_depth=32 if mcts.max_depth is None else mcts.max_depth,
    )
