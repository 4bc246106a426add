"""The training methods: what one action is, who plays the episodes, and each method's own settings.

- rl-lock: MCTS over whole pieces (the paper's method; `rllock.search.mcts.ChunkStore`).
- rl-lock-action: MCTS over single voxels (the paper's RL-Lock_Action; `rllock.search.voxel_search`).
- ppo: no search; actions drawn from the network's masked policy over voxels (the paper's PPO baseline;
  `rllock.search.ppo`).
"""

from __future__ import annotations

import dataclasses

from rllock.config import METHODS, MCTSConfig, NetConfig, TrainConfig
from rllock.core.env import Task
from rllock.errors import RLLockError
from rllock.search.base import Player, group_sizes
from rllock.search.mcts import ChunkStore, NodeStore, searchers
from rllock.search.network import PolicyValueNet
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
) -> list[Player]:
    """Who plays `episodes` episodes in `groups` lockstep groups (see `rllock.search.mcts.play_groups`)."""
    if method == "ppo":
        return [PolicyPlayer(PolicyValueNet(net), mcts, task, size) for size in group_sizes(episodes, groups)]
    return searchers(net, mcts, space(method), task, episodes, groups)


def with_method_defaults(config: TrainConfig) -> TrainConfig:
    """`config` with the method's own settings where it holds the general defaults.
    - rl-lock-action: 128 simulations per voxel decision and depth at most 32 (the paper's section 5).
    - ppo: near on-policy learning: a buffer of the freshest 2,048 transitions, each sampled about 4
      times (as 4 epochs would), and self-play at most one weights version behind."""
    general = TrainConfig()
    if config.method == "rl-lock-action":
        mcts = config.mcts
        return dataclasses.replace(
            config,
            mcts=dataclasses.replace(
                mcts,
                simulations=128 if mcts.simulations == general.mcts.simulations else mcts.simulations,
                max_depth=32 if mcts.max_depth is None else mcts.max_depth,
            ),
        )
    if config.method == "ppo":

        def unless_given(name: str, value):
            return value if getattr(config, name) == getattr(general, name) else getattr(config, name)

        return dataclasses.replace(
            config,
            buffer_capacity=unless_given("buffer_capacity", 2048),
            replay_ratio=unless_given("replay_ratio", 4.0),
            max_policy_lag=unless_given("max_policy_lag", 1),
        )
    return config
