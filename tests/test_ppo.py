"""PPO: the loss against a plain computation, and rollouts drawn from the masked policy."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from rllock.core.env import final_labels, make_task
from rllock.core.verifier import verify_labels
from rllock.core.voxel_env import initial_voxel_state, legal_mask, step
from rllock.search.mcts import MCTSConfig
from rllock.search.network import NetConfig, PolicyValueNet, init_params
from rllock.search.ppo import PolicyPlayer, ppo_loss

NET = NetConfig(canvas=4, features=(4, 8))


def _reference_loss(
    voxel_logits, value, chunks, valid, behaviour, actions, z, clip, value_coef, entropy_coef
):
    """The PPO loss written out with numpy, one transition at a time."""
    terms, values, entropies = [], [], []
    advantage = z - value
    advantage = (advantage - advantage.mean()) / (advantage.std() + 1e-8)
    for b in range(len(z)):
        logits = np.array([voxel_logits[b, chunks[b, m]].mean() for m in range(chunks.shape[1])])
        logits = np.where(valid[b], logits, -np.inf)
        log_p = logits - np.log(np.sum(np.exp(logits - logits.max()))) - logits.max()
        ratio = np.exp(log_p[actions[b]] - np.log(behaviour[b, actions[b]]))
        clipped = np.clip(ratio, 1 - clip, 1 + clip)
        terms.append(-min(ratio * advantage[b], clipped * advantage[b]))
        values.append((z[b] - value[b]) ** 2)
        p = np.exp(log_p[valid[b]])
        entropies.append(-np.sum(p * np.log(p)))
    return np.mean(terms) + value_coef * np.mean(values) - entropy_coef * np.mean(entropies)


def test_ppo_loss_matches_a_plain_computation():
    rng = np.random.default_rng(0)
    net = PolicyValueNet(NET)
    params = init_params(NET, jax.random.PRNGKey(1))
    batch, m = 6, 5
    planes = rng.random((batch, 4, 4, 4, 7)).astype(np.float32)
    chunks = rng.integers(0, 64, size=(batch, m, 1)).astype(np.int32)
    valid = np.ones((batch, m), bool)
    valid[:, 3:] = rng.random((batch, 2)) < 0.5
    behaviour = np.where(valid, rng.random((batch, m)) + 0.1, 0.0).astype(np.float32)
    behaviour /= behaviour.sum(axis=1, keepdims=True)
    actions = np.array([rng.choice(np.flatnonzero(v)) for v in valid], np.int32)
    z = rng.choice([0.0, 0.25, 0.5, 0.75], size=batch).astype(np.float32)
    settings = dict(clip=0.2, value_coef=0.5, entropy_coef=0.01)
    total, (policy, value_loss, entropy) = ppo_loss(
        params, net, planes, chunks, valid, behaviour, actions, z, **settings
    )
    voxel_logits, value = net.apply({"params": params}, planes)
    want = _reference_loss(
        np.asarray(voxel_logits, np.float64), np.asarray(value, np.float64), chunks, valid, behaviour,
        actions, z, *settings.values(),
    )  # fmt: skip
    assert float(total) == pytest.approx(want, rel=1e-4, abs=1e-5)
    assert np.isfinite([float(policy), float(value_loss), float(entropy)]).all() and float(entropy) > 0


def test_rollouts_draw_legal_voxels_and_record_the_behaviour_policy():
    task = make_task("box:4x4x2", 3)
    player = PolicyPlayer(PolicyValueNet(NET), MCTSConfig(), task, batch=16)
    episodes = player.play(init_params(NET, jax.random.PRNGKey(0)), task, jax.random.PRNGKey(2), seed=1)
    assert len(episodes) == 16
    for e in episodes:
        state = initial_voxel_state(task)
        for s in range(len(e.z)):
            m = int(e.num_valid[s])
            assert sorted(e.chunks[s, :m, 0].tolist()) == np.flatnonzero(legal_mask(task, state)).tolist()
            assert 0 <= e.actions[s] < m and e.pi[s, e.actions[s]] > 0
            assert np.isclose(e.pi[s, :m].sum(), 1, atol=1e-5) and np.allclose(e.pi[s, m:], 0)
            assert e.z[s] == pytest.approx((e.final.placed - state.placed) / task.pieces)
            state, _ = step(task, state, int(e.chunks[s, e.actions[s], 0]))
        np.testing.assert_array_equal(state.labels, e.final.labels)
        if e.success:
            assert verify_labels(task.topology.to_grid(final_labels(task, e.final))).valid
