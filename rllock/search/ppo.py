"""The paper's PPO baseline: a masked policy over voxel actions (`rllock.core.voxel_env`) with the same U-Net
and value head, trained with PPO's clipped objective.

- Rollouts: episodes in lockstep, one network call per step for all of them; each action is drawn from
  the softmax over the legal voxels at temperature 1, at training and at inference alike (the paper's
  setting). An episode is stored like a search episode (`rllock.search.base.Episode`): the candidates are the
  legal voxels, `pi` the behaviour policy's probabilities and `actions` the voxels taken.
- Returns: discount 1, so an action's return is the reward still to come, (pieces accepted at the end -
  pieces accepted before it) / K, as in the search methods.
- Advantages: the return minus the current value estimate (Monte Carlo with a learned baseline, no GAE),
  normalised over the mini-batch.
- Loss: -min(r A, clip(r, 1 - eps, 1 + eps) A) + c_v (z - v)^2 - c_e H(p), with r the ratio of the new
  to the behaviour probability of the action taken.
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

from rllock.config import MCTSConfig
from rllock.core.env import Task
from rllock.search.base import Episode, TimeSplit
from rllock.search.mcts import play_lockstep
from rllock.search.network import PolicyValueNet, chunk_logits
from rllock.search.nodes import node_features
from rllock.search.voxel_search import VoxelStore


def ppo_loss(
    params,
    net: PolicyValueNet,
    planes,
    chunks,
    valid,
    behaviour,
    actions,
    z,
    *,
    clip: float,
    value_coef: float,
    entropy_coef: float,
):
    """The PPO loss of a batch (module docstring); also (policy term, value term, entropy)."""
    voxel_logits, value = net.apply({"params": params}, planes)
    log_p = jax.nn.log_softmax(chunk_logits(voxel_logits, chunks, valid), axis=-1)
    rows = jnp.arange(actions.shape[0])
    new = log_p[rows, actions]
    old = jnp.log(jnp.maximum(behaviour[rows, actions], 1e-12))
    ratio = jnp.exp(new - old)
    advantage = z - jax.lax.stop_gradient(value)
    advantage = (advantage - advantage.mean()) / (advantage.std() + 1e-8)
    policy = -jnp.minimum(ratio * advantage, jnp.clip(ratio, 1 - clip, 1 + clip) * advantage).mean()
    value_loss = jnp.mean((z - value) ** 2)
    entropy = -jnp.sum(jnp.where(valid, jnp.exp(log_p) * log_p, 0.0), axis=-1).mean()
    return policy + value_coef * value_loss - entropy_coef * entropy, (policy, value_loss, entropy)


class PolicyPlayer:
    """Plays lockstep batches of `batch` episodes by sampling from the network's masked policy: the PPO
    counterpart of `rllock.search.mcts.Searcher`, with the same `play` signature."""

    def __init__(self, net: PolicyValueNet, config: MCTSConfig, task: Task, batch: int):
        self.config = config
        self.canvas = net.config.canvas_side()
        self.task_planes = net.config.task_planes
        self.batch = batch

        def policy(params, key, planes, chunks, valid):
            voxel_logits, _ = net.apply({"params": params}, planes)
            logits = chunk_logits(voxel_logits, chunks, valid)
            return jax.random.categorical(key, logits, axis=-1), jax.nn.softmax(logits, axis=-1)

        self._policy = jax.jit(policy)

    def play(
        self,
        params,
        task: Task,
        key: jax.Array,
        *,
        seed: int,
        times: TimeSplit | None = None,
        parallel: bool = True,
    ) -> list[Episode]:
        """`batch` episodes from the empty state, each action drawn from the masked policy."""
        del parallel  # the legal masks are cheap: no threads needed
        store = VoxelStore(task, self.config, self.canvas, seed, task_planes=self.task_planes)

        def decide(sub: jax.Array, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            planes, chunks, valid = node_features(store, nodes)
            valid[~valid.any(axis=1), 0] = True  # finished rows still run: keep them finite
            start = time.perf_counter()
            actions, probs = (np.asarray(a) for a in self._policy(params, sub, planes, chunks, valid))
            store.times.network += time.perf_counter() - start
            return actions, probs

        return play_lockstep(store, self.batch, decide, key, times)
