"""Pure pacing rules of the actor-learner loop (`rllock.orchestration.loop`), for both trainers: no Ray, no
clocks of their own (times are passed in), so each rule is unit-tested in milliseconds."""

from __future__ import annotations

import math
from dataclasses import dataclass

from rllock.config import TrainConfig

RESERVE_S = 20.0
"""Seconds of the budget kept for the last checkpoint and shutting Ray down."""
REPORT_EVERY_S = 30.0


@dataclass(frozen=True)
class Pacing:
    """When the learner may step. A trainer without a lag limit (its actors take the newest weights at
    every call) has `max_policy_lag` None; one that learns from data already made has an infinite
    `replay_ratio`."""

    warmup: int
    """Transitions in the buffer before the first step."""
    batch_size: int
    replay_ratio: float
    max_policy_lag: int | None
    max_learner_steps: int | None

    @staticmethod
    def of(config: TrainConfig) -> Pacing:
        return Pacing(
            config.warmup,
            config.learner.batch_size,
            config.replay_ratio,
            config.max_policy_lag,
            config.max_learner_steps,
        )

    def can_learn(self, *, step: int, transitions: int, version: int, oldest_version: int) -> bool:
        """Whether the learner may take step `step + 1` now: enough data, under the replay ratio, and
        no batch in flight is `max_policy_lag` versions behind."""
        return (
            not self.reached_max(step)
            and transitions >= max(self.warmup, 1)
            and (step + 1) * self.batch_size <= self.replay_ratio * transitions
            and (self.max_policy_lag is None or version - oldest_version < self.max_policy_lag)
        )

    def reached_max(self, step: int) -> bool:
        return self.max_learner_steps is not None and step >= self.max_learner_steps


@dataclass
class Schedule:
    """When periodic work is due (monotonic seconds). A policy run's first checkpoint is due as soon as
    there is a learner step, so a killed run loses little; later ones every `checkpoint_s`."""

    deadline: float
    checkpoint_s: float
    validate_s: float
    next_validate: float
    next_report: float
    next_checkpoint: float | None = None  # None: at the first learner step

    @staticmethod
    def start(now: float, config: TrainConfig) -> Schedule:
        """A policy run's (`rllock train`)."""
        return Schedule.of(
            now,
            minutes=config.minutes,
            checkpoint_minutes=config.checkpoint_minutes,
            validate_minutes=config.validate_minutes,
        )

    @staticmethod
    def of(
        now: float,
        *,
        minutes: float,
        checkpoint_minutes: float,
        validate_minutes: float = math.inf,
        reserve_s: float = RESERVE_S,
        checkpoint_first_step: bool = True,
    ) -> Schedule:
        """A run of `minutes` from `now` whose work stops `reserve_s` before their end; without
        `checkpoint_first_step`, the first checkpoint is due `checkpoint_minutes` after `now`."""
        return Schedule(
            deadline=now + 60 * minutes - reserve_s,
            checkpoint_s=60 * checkpoint_minutes,
            validate_s=60 * validate_minutes,
            next_validate=now + 60 * validate_minutes,
            next_report=now + REPORT_EVERY_S,
            next_checkpoint=None if checkpoint_first_step else now + 60 * checkpoint_minutes,
        )

    def over(self, now: float) -> bool:
        return now >= self.deadline

    def checkpoint_due(self, now: float, step: int) -> bool:
        if step == 0:
            return False
        return self.next_checkpoint is None or now >= self.next_checkpoint

    def checkpointed(self, now: float) -> None:
        self.next_checkpoint = now + self.checkpoint_s

    def validation_due(self, now: float) -> bool:
        return now >= self.next_validate

    def validated(self, now: float) -> None:
        self.next_validate = now + self.validate_s

    def report_due(self, now: float) -> bool:
        if now < self.next_report:
            return False
        self.next_report = now + REPORT_EVERY_S
        return True

    def fits(self, now: float, seconds: float | None, *, final: bool = False) -> bool:
        """Whether work expected to take `seconds` (None: unknown) ends before the deadline; the final
        validation may also use half of the reserve kept for the last checkpoint and shutdown."""
        slack = RESERVE_S / 2 if final else 0.0
        return seconds is not None and now + seconds <= self.deadline + slack


COMPILE_S = 20.0
"""Allowance for compiling the validation's search the first time (a lockstep batch of its own size)."""
FINAL_SHARE = 0.25
"""The final validation may take at most this share of the budget; a dearer one is skipped."""


def validation_estimate(
    batch_seconds: float | None,
    batch_episodes: int,
    groups: int,
    episodes: int,
    last_validation_s: float | None,
) -> float | None:
    """Expected seconds of a validation of `episodes` lockstep episodes in one group on one core: the last
    one's time when there was one, else scaled from a self-play batch of `batch_episodes` episodes played
    in `groups` groups on as many cores (lockstep cost grows about linearly with the episodes), plus the
    first compile."""
    if last_validation_s is not None:
        return last_validation_s
    if batch_seconds is None:
        return None
    return batch_seconds * groups * episodes / max(batch_episodes, 1) + COMPILE_S


def final_reserve(estimate: float | None, config: TrainConfig) -> float:
    """Seconds to stop self-play early by, so that the final validation fits the budget: its estimate
    when that is known and at most FINAL_SHARE of the budget, else 0 (the validation is then skipped)."""
    if estimate is None or estimate > FINAL_SHARE * 60 * config.minutes:
        return 0.0
    return estimate
