"""The training methods: what one action is and who plays the episodes (each method's own settings are
`rllock.config.METHOD_DEFAULTS`).

- rl-lock: MCTS over whole pieces (the paper's method; `rllock.search.mcts.ChunkStore`).
- rl-lock-action: MCTS over single voxels (the paper's RL-Lock_Action; `rllock.search.voxel_search`).
- ppo: no search; actions drawn from the network's masked policy over voxels (the paper's PPO baseline;
  `rllock.search.ppo`).
"""

from __future__ import annotations

from collections.abc import Sequence

from rllock.config import METHODS, MCTSConfig, NetConfig
from rllock.core.env import Task
from rllock.errors import RLLockError
from rllock.search.base import Player, group_sizes
from rllock.search.mcts import ChunkStore, searchers
from rllock.search.network import PolicyValueNet
from rllock.search.nodes import NodeStore
from rllock.search.ppo import PolicyPlayer
from rllock.search.voxel_search import VoxelStore

SPACES: dict[str, type[NodeStore]] = {"rl-lock": ChunkStore, "rl-lock-action": VoxelStore, "ppo": VoxelStore}
assert tuple(SPACES) == METHODS


def space(method: str) -> type[NodeStore]:
    """What one action of `method` is (for PPO: the voxel actions its policy chooses among)."""
    try:
        return SPACES[method]
    except KeyError:
        raise RLLockError(f"unknown method {method!r}: use one of {', '.join(METHODS)}") from None


def players(
    method: str, net: NetConfig, mcts: MCTSConfig, task: Task, episodes: int, groups: int
) -> Sequence[Player]:
    """Who plays `episodes` episodes in `groups` lockstep groups (see `rllock.search.mcts.play_groups`)."""
    if method == "ppo":
        return [PolicyPlayer(PolicyValueNet(net), mcts, task, size) for size in group_sizes(episodes, groups)]
    return searchers(net, mcts, space(method), task, episodes, groups)
