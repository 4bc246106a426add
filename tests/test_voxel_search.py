"""RL-Lock_Action: MCTS over voxel actions in the batched search, and its episodes."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from helpers import untrained_episodes

from rllock.config import TrainConfig, with_method_defaults
from rllock.core.env import final_labels
from rllock.core.verifier import verify_labels
from rllock.core.voxel_env import initial_voxel_state, legal_mask, step
from rllock.search.mcts import MCTSConfig
from rllock.search.voxel_search import VoxelStore

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


def test_each_method_takes_its_own_settings_unless_others_are_given():
    base = TrainConfig(shape="cube4", pieces=7)
    action = with_method_defaults(dataclasses.replace(base, method="rl-lock-action"), given=())
    assert (action.mcts.simulations, action.mcts.max_depth, action.mcts.max_considered) == (128, 32, 16)
    given = with_method_defaults(
        dataclasses.replace(base, method="rl-lock-action", mcts=MCTSConfig(simulations=64, max_depth=8)),
        given={"simulations", "max_depth"},
    )
    assert (given.mcts.simulations, given.mcts.max_depth) == (64, 8)
    ppo = with_method_defaults(
        dataclasses.replace(base, method="ppo", replay_ratio=2.0), given={"replay_ratio"}
    )
    assert (ppo.buffer_capacity, ppo.replay_ratio, ppo.max_policy_lag) == (2048, 2.0, 1)
    assert with_method_defaults(base, given=()) == base


@pytest.mark.parametrize(
    "flags, want",
    [
        ([], (128, 32, 50_000, 4.0)),
        # A flag the user gives wins even when it equals the general default (256 simulations, 4.0).
        (["--simulations", "256"], (256, 32, 50_000, 4.0)),
        (["--simulations=256", "--max-depth", "8"], (256, 8, 50_000, 4.0)),
    ],
)
def test_a_flag_the_user_gives_always_wins_over_the_method_defaults(flags, want):
    from rllock.orchestration.cli.main import build_parser
    from rllock.orchestration.cli.training import train_config

    args = build_parser().parse_args(
        ["train", "--shape", "cube4", "--pieces", "7", "--method", "rl-lock-action", *flags]
    )
    config = train_config(args)
    assert (
        config.mcts.simulations,
        config.mcts.max_depth,
        config.buffer_capacity,
        config.replay_ratio,
    ) == want


def test_ppo_keeps_a_replay_ratio_given_equal_to_the_general_default():
    from rllock.orchestration.cli.main import build_parser
    from rllock.orchestration.cli.training import train_config

    def parse(*flags: str):
        return train_config(build_parser().parse_args(["train", "--shape", "cube4", "--pieces", "7", *flags]))

    given = parse("--method", "ppo", "--replay-ratio", "4")
    default = parse("--method", "ppo", "--no-symmetries")
    assert (given.replay_ratio, given.buffer_capacity, given.max_policy_lag) == (4.0, 2048, 1)
    assert (default.replay_ratio, default.buffer_capacity, default.learner.symmetries) == (4.0, 2048, False)
    plain = parse("--replay-ratio", "2")
    assert (plain.replay_ratio, plain.buffer_capacity, plain.mcts.simulations) == (2.0, 50_000, 256)
