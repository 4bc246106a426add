"""The loop's pure pacing rules, in milliseconds."""

from __future__ import annotations

from rllock.config import LearnerConfig, TrainConfig
from rllock.orchestration.pacing import (
    COMPILE_S,
    RESERVE_S,
    Pacing,
    Schedule,
    final_reserve,
    validation_estimate,
)

PACING = Pacing(warmup=64, batch_size=64, replay_ratio=4.0, max_policy_lag=4, max_learner_steps=10)


def test_learning_waits_for_a_batch_of_data_and_respects_the_replay_ratio():
    assert not PACING.can_learn(step=0, transitions=63, version=0, oldest_version=0)
    assert PACING.can_learn(step=0, transitions=64, version=0, oldest_version=0)
    # 64 transitions allow 4 * 64 sampled ones: steps 1..4, not a fifth.
    assert PACING.can_learn(step=3, transitions=64, version=0, oldest_version=0)
    assert not PACING.can_learn(step=4, transitions=64, version=0, oldest_version=0)


def test_policy_lag_and_step_limit_stop_the_learner():
    assert not PACING.can_learn(step=1, transitions=1000, version=5, oldest_version=1)
    assert PACING.can_learn(step=1, transitions=1000, version=4, oldest_version=1)
    assert not PACING.can_learn(step=10, transitions=10_000, version=0, oldest_version=0)
    assert PACING.reached_max(10) and not PACING.reached_max(9)
    assert not Pacing(1, 1, 1.0, 1, None).reached_max(10**9)


def test_the_default_warmup_is_one_batch():
    config = TrainConfig(shape="cube4", pieces=5, learner=LearnerConfig(batch_size=32))
    assert Pacing.of(config).warmup == 32
    assert Pacing.of(TrainConfig(shape="cube4", pieces=5, min_buffer=500)).warmup == 500


def test_schedule_keeps_the_budget_and_checkpoints_right_after_the_first_step():
    config = TrainConfig(shape="cube4", pieces=5, minutes=3.0, checkpoint_minutes=2.0, validate_minutes=1.0)
    s = Schedule.start(100.0, config)
    assert s.deadline == 100.0 + 180.0 - RESERVE_S
    assert not s.checkpoint_due(101.0, step=0)
    assert s.checkpoint_due(101.0, step=1)  # the first learner step: checkpoint now
    s.checkpointed(101.0)
    assert not s.checkpoint_due(220.0, step=50) and s.checkpoint_due(221.0, step=50)
    assert not s.validation_due(159.0) and s.validation_due(160.0)
    assert s.fits(200.0, 50.0) and not s.fits(200.0, 70.0) and not s.fits(0.0, None)
    assert s.fits(200.0, 70.0, final=True) and not s.fits(200.0, 71.0, final=True)
    assert s.report_due(130.0) and not s.report_due(131.0)
    assert not s.over(259.9) and s.over(260.0)


def test_validation_estimates_scale_a_selfplay_batch_or_reuse_the_last_validation():
    assert validation_estimate(None, 8, 1, 64, None) is None
    assert validation_estimate(10.0, 8, 1, 64, None) == 80.0 + COMPILE_S
    # Two groups on two cores: one core alone takes twice as long per episode.
    assert validation_estimate(10.0, 8, 2, 64, None) == 160.0 + COMPILE_S
    assert validation_estimate(10.0, 8, 2, 64, 33.0) == 33.0


def test_the_final_validation_gets_its_time_only_when_it_is_a_small_share_of_the_budget():
    config = TrainConfig(shape="cube4", pieces=5, minutes=4.0)
    assert final_reserve(None, config) == 0.0
    assert final_reserve(50.0, config) == 50.0
    assert final_reserve(61.0, config) == 0.0  # over a quarter of 240 s: skipped, training keeps the time


def test_a_guide_run_keeps_no_reserve_checkpoints_on_the_clock_and_has_no_lag_limit():
    s = Schedule.of(100.0, minutes=2.0, checkpoint_minutes=1.0, reserve_s=0.0, checkpoint_first_step=False)
    assert s.deadline == 220.0 and not s.validation_due(10**9)
    assert not s.checkpoint_due(101.0, step=1) and s.checkpoint_due(160.0, step=1)
    pacing = Pacing(warmup=16, batch_size=16, replay_ratio=4.0, max_policy_lag=None, max_learner_steps=None)
    assert pacing.can_learn(step=0, transitions=16, version=100, oldest_version=0)
    assert not pacing.can_learn(step=4, transitions=16, version=0, oldest_version=0)
