"""RL-Lock_Action: MCTS over voxel actions in the batched search, and its episodes."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import untrained_episodes

from rllock.env import final_labels
from rllock.mcts import MCTSConfig
from rllock.methods import with_method_defaults
from rllock.verifier import verify_labels
from rllock.voxel_env import initial_voxel_state, legal_mask, step
from rllock.voxel_search import VoxelStore

SMALL = MCTSConfig(simulations=8, max_considered=4, max_depth=6)


@pytest.fixture(scope="module")
def episodes():
    return untrained_episodes(VoxelStore, SMALL, batch=8, seed=5)  # n = 10: 20 voxel decisions


def test_voxel_episodes_take_legal_voxels_and_score_only_accepted_pieces(episodes):
    task, eps = episodes
    assert any(e.success for e in eps) and not all(e.success for e in eps)
    for e in eps:
        state = initial_voxel_state(task)
        t = len(e.z)
        for s in range(t):
            m = int(e.num_valid[s])
            np.testing.assert_array_equal(e.labels[s], state.labels)
            # Candidates are exactly the legal voxels, as one-voxel chunks; the encoding marks the
            # growing piece (placed + 1) once it has a voxel.
            assert sorted(e.chunks[s, :m, 0].tolist()) == np.flatnonzero(legal_mask(task, state)).tolist()
            assert e.placed[s] == state.placed + (state.filled > 0)
            assert np.isclose(e.pi[s, :m].sum(), 1, atol=1e-5) and np.allclose(e.pi[s, m:], 0)
            assert e.z[s] == pytest.approx((e.final.placed - state.placed) / task.pieces)
            if s + 1 < t:  # the next state is reached by one of the candidates
                options = [step(task, state, int(v))[0] for v in e.chunks[s, :m, 0]]
                state = next(o for o in options if np.array_equal(o.labels, e.labels[s + 1]))
        assert e.success == (e.final.placed == task.pieces - 1)
        if e.success:
            assert verify_labels(task.topology.to_grid(final_labels(task, e.final))).valid
        else:
            assert e.final.failed or not legal_mask(task, e.final).any()


def test_rl_lock_action_takes_the_papers_settings_unless_others_are_given():
    general = MCTSConfig()
    baseline = with_method_defaults("rl-lock-action", general)
    assert (baseline.simulations, baseline.max_depth, baseline.max_considered) == (128, 32, 16)
    given = with_method_defaults("rl-lock-action", MCTSConfig(simulations=64, max_depth=8))
    assert (given.simulations, given.max_depth) == (64, 8)
    assert with_method_defaults("rl-lock", general) == general
