"""`rllock train`: self-play actors on Ray, a replay buffer actor, and the JAX learner in this process,
run by the actor-learner loop (`rllock.orchestration.loop`) with the parts `rllock.orchestration.builder`
makes.

Each actor plays a lockstep batch of episodes with the weights version it was handed, pushes the episodes
into the replay buffer actor and returns its statistics; the learner stops publishing while the oldest
batch in flight is `max_policy_lag` versions behind (`pacing.Pacing`). The learner starts once the buffer
holds a batch, takes at most `replay_ratio` sampled transitions per transition produced, validates on
fixed seeds (`validation`) every `validate_minutes` when the budget has room for it, and keeps:
  LOGDIR/checkpoints/<step>/  the latest checkpoints (orbax: learner state + metadata with the config,
                              the task and the counters); the first right after the first learner step
  LOGDIR/best/<step>/         the checkpoint with the best validation
  LOGDIR/best_assembly/       the best validation assembly so far (verified), with its picture
  LOGDIR/replay.npz           the replay buffer, snapshotted atomically with every checkpoint
  TensorBoard event files
`--minutes` is a hard budget: the run returns within it plus 30 s, its last checkpoint included.
`rllock train --resume LOGDIR` continues from the newest readable checkpoint (an unreadable one is
skipped with a warning) with its config, optimizer state, PRNG key, counters, best score and replay
buffer. Ctrl-C stops cleanly: a final checkpoint and snapshot, then Ray is shut down.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

from rllock.actors.selfplay import PlayStats, PlayTotals
from rllock.config import TrainConfig
from rllock.orchestration import validation
from rllock.orchestration.builder import SelfPlayBuilder, run
from rllock.orchestration.loop import System
from rllock.orchestration.pacing import final_reserve
from rllock.orchestration.pool import NodeWatch
from rllock.orchestration.stopping import signal_name
from rllock.orchestration.validation import Score
from rllock.process import peak_rss_mb

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrainResult:
    """What a run did (`train`'s return value)."""

    steps: int
    episodes: int
    selfplay_success_rate: float
    validation: Score | None  # the last validation's
    best_success_rate: float  # -1: none yet
    seconds: float
    episodes_per_sec: float
    simulations_per_sec: float
    actors: int
    logdir: str
    interrupted: bool
    stop_signal: int | None  # the signal that stopped the run (SIGINT or SIGTERM)
    peak_rss_mb: dict[str, float]  # peak resident MiB of the driver, the buffer and an actor


def train(config: TrainConfig, *, resume: bool = False) -> TrainResult:
    began = time.monotonic()
    builder = SelfPlayBuilder(config, resume=resume)
    loop = run(builder, lambda system: SelfPlayWatch(builder, system), resume=resume, began=began)
    if loop.stop.requested:
        log.warning(
            "stopped by %s at learner step %d; checkpoint saved. Resume with: rllock train --resume %s",
            signal_name(loop.stop.signum),
            builder.learner.step,
            builder.logdir,
        )
    return loop.monitor.result(time.monotonic() - began, loop.stop.signum)


@dataclass
class Progress:
    """What the run has seen of self-play: the policy lag, the fastest batch (the first includes
    compiling; it sizes a validation), the buffer's successful transitions and peak memory."""

    lag: int = 0
    batch_seconds: float | None = None
    buffer_successes: int = 0
    memory: dict[str, float] = field(default_factory=lambda: {"driver": 0.0, "buffer": 0.0, "actor": 0.0})

    def add(self, stats: PlayStats, version: int) -> None:
        """A finished batch, `version` being the weights version now."""
        self.lag = version - stats.version
        self.batch_seconds = min(stats.seconds, self.batch_seconds or stats.seconds)
        self.memory["actor"] = max(self.memory["actor"], stats.peak_rss_mb)
        if stats.buffer is not None:
            self.buffer_successes = stats.buffer.successes
            self.memory["buffer"] = stats.buffer.peak_rss_mb


class SelfPlayWatch:
    """What a policy run watches beside the loop (`rllock.orchestration.loop.Monitor`): self-play's progress,
    the cluster's nodes, charts and a log line every 30 s, and validations on schedule when the budget
    has room for them (the final one's time kept at the end)."""

    def __init__(self, builder: SelfPlayBuilder, system: System):
        self.config, self.learner, self.pool = builder.config, builder.learner, builder.pool
        self.totals: PlayTotals = builder.totals
        self.counters, self.recorder, self.schedule = system.counters, system.recorder, system.schedule
        self.validator = validation.Validator(
            validation.Plan.of(self.config, builder.workload), builder.last_score
        )
        self.progress = Progress()
        self.nodes = NodeWatch.start()

    def count(self, stats: PlayStats) -> None:
        self.progress.add(stats, self.counters.version)

    def periodic(self, now: float) -> None:
        self.nodes.check(now, self.pool)
        if self.schedule.report_due(now):
            self._charts()
            self._report()
        if self.schedule.validation_due(now):
            self._validate_if_it_fits(now, final=False)
            self.schedule.validated(time.monotonic())

    def reserve(self) -> float:
        return final_reserve(self._validation_estimate(), self.config)

    def score(self) -> dict | None:
        last = self.validator.last
        return None if last is None else last.to_json()

    def checkpointed(self) -> None:
        pass

    def final(self, now: float, *, stopped: bool) -> None:
        if not stopped:
            self._validate_if_it_fits(now, final=True)
        self._charts()  # the curves end at the final step

    def result(self, seconds: float, stop_signal: int | None) -> TrainResult:
        t, elapsed = self.totals, max(self.counters.seconds, 1e-9)
        return TrainResult(
            steps=self.learner.step,
            episodes=t.episodes,
            selfplay_success_rate=t.successes / max(t.episodes, 1),
            validation=self.validator.last,
            best_success_rate=(self.counters.best or (-1.0, -1.0))[0],
            seconds=seconds,
            episodes_per_sec=t.episodes / elapsed,
            simulations_per_sec=t.simulations / elapsed,
            actors=self.pool.layout.actors,
            logdir=str(self.recorder.logdir),
            interrupted=stop_signal is not None,
            stop_signal=stop_signal,
            peak_rss_mb=dict(self.progress.memory),
        )

    def _report(self) -> None:
        t, p, last = self.totals, self.progress, self.validator.last
        log.info(
            "step %d | episodes %d | self-play success %.1f%% | validation %s | lag %d | "
            "peak MiB driver %.0f buffer %.0f actor %.0f | %.0f s",
            self.learner.step,
            t.episodes,
            100 * t.successes / max(t.episodes, 1),
            "-" if last is None else f"{100 * last.success_rate:.1f}%",
            p.lag,
            p.memory["driver"],
            p.memory["buffer"],
            p.memory["actor"],
            self.counters.seconds,
        )

    def _charts(self) -> None:
        self.progress.memory["driver"] = peak_rss_mb()
        values = chart_values(
            self.totals, self.progress, self.counters.seconds, self.learner.step, self.config.buffer_capacity
        )
        self.recorder.scalars(values, self.learner.step)

    def _validation_estimate(self) -> float | None:
        return self.validator.estimate(self.progress.batch_seconds, self.pool.layout)

    def _validate_if_it_fits(self, now: float, *, final: bool) -> None:
        estimate = self._validation_estimate()
        if self.schedule.fits(now, estimate, final=final):
            self.validator.run(self.learner, self.recorder, self.counters)
            return
        need = (
            "no self-play batch has finished yet to time it"
            if estimate is None
            else f"about {estimate:.0f} s of the budget would be needed"
        )
        left = max(0.0, self.schedule.deadline - now)
        log.info("%svalidation skipped: %s, %.0f s are left", "final " if final else "", need, left)


def chart_values(t: PlayTotals, p: Progress, seconds: float, step: int, capacity: int) -> dict[str, float]:
    """The run's TensorBoard charts: throughput, policy lag, self-play success, buffer and memory."""
    seconds = max(seconds, 1e-9)
    return {
        "charts/episodes_per_sec": t.episodes / seconds,
        "charts/simulations_per_sec": t.simulations / seconds,
        "charts/learner_steps_per_sec": step / seconds,
        "charts/policy_lag": p.lag,
        "charts/selfplay_success_rate": t.successes / max(t.episodes, 1),
        "buffer/size": min(t.transitions, capacity),
        "buffer/success_transitions": p.buffer_successes,
        **{f"memory/{kind}_peak_mb": mb for kind, mb in p.memory.items()},
    }
