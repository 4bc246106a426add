"""`rllock train`: self-play actors on Ray, a replay buffer actor, and the JAX learner in this process.

Data flow: each actor plays a lockstep batch of episodes with the weights version it was handed, pushes
the episodes into the replay buffer actor and returns its statistics; this process then hands it the
newest weights (one `ray.put` per version, fetched by an actor only when the version changed). Exactly
one batch is in flight per actor, and the learner stops publishing while the oldest batch in flight is
`max_policy_lag` versions behind (`pacing.Pacing`). The learner starts once the buffer holds a batch,
takes at most `replay_ratio` sampled transitions per transition produced, validates on fixed seeds
(`validation`) every `validate_minutes` when the budget has room for it, and keeps:
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
from pathlib import Path
from typing import Any

import jax
import ray

from learner.learner import Learner
from orchestration import validation
from orchestration.builder import Start, start_buffer, start_learner, start_pool, workload_of
from orchestration.pacing import Pacing, Schedule, final_reserve
from orchestration.pool import NodeWatch, start_ray
from orchestration.recorder import Counters, Recorder
from orchestration.stopping import StopRequest, signal_name, stop_on_signals
from orchestration.validation import Score
from rllock.config import TrainConfig
from rllock.errors import RLLockError
from rllock.files import checkpoint as ckpt
from rllock.process import peak_rss_mb
from rllock.search.workload import Workload

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
    config.validate()
    config, workload, init = workload_of(config, resume=resume)
    logdir = Path(config.logdir)
    if not resume and ckpt.saved_steps(logdir / "checkpoints"):
        raise RLLockError(
            f"{logdir} already holds a training run; resume it with --resume {logdir} "
            f"or choose another --logdir"
        )
    # Ray starts its processes with fork() (and Python code in the child): after JAX has started its
    # threads, with the learner's first array, that can deadlock. So Ray starts first.
    started_ray = start_ray(config.address)
    try:
        learner, start = start_learner(config, workload, init, resume)
        recorder = Recorder(logdir, config, workload.identity(), learner.step, resume, start.sessions)
        run = _Run(config, workload, learner, recorder, start, began)
        try:
            with stop_on_signals(run.stop):
                return run.loop(resume)
        finally:
            recorder.close()
            if run.stop.requested:
                log.warning(
                    "stopped by %s at learner step %d; checkpoint saved. Resume with: "
                    "rllock train --resume %s",
                    signal_name(run.stop.signum),
                    learner.step,
                    logdir,
                )
    finally:
        if started_ray:
            ray.shutdown()


@dataclass
class _Progress:
    """What the loop has seen of self-play: the policy lag, the fastest batch (the first includes
    compiling; it sizes a validation), the buffer's successful transitions and peak memory."""

    lag: int = 0
    batch_seconds: float | None = None
    buffer_successes: int = 0
    memory: dict[str, float] = field(default_factory=lambda: {"driver": 0.0, "buffer": 0.0, "actor": 0.0})


class _Run:
    """The actor-learner loop: self-play batches in, learner steps, published weights, checkpoints and
    validations on schedule; its state is what a checkpoint must capture."""

    def __init__(
        self,
        config: TrainConfig,
        workload: Workload,
        learner: Learner,
        recorder: Recorder,
        start: Start,
        began: float,
    ):
        self.config, self.workload = config, workload
        self.learner, self.recorder, self.counters = learner, recorder, start.counters
        self.pacing = Pacing.of(config)
        self.began = began
        self.schedule = Schedule.start(began, config)
        self.validator = validation.Validator(validation.Plan.of(config, workload), start.last_score)
        self.progress = _Progress()
        self.stop = StopRequest()

    def loop(self, resume: bool) -> TrainResult:
        self.buffer: Any = start_buffer(self.config, self.workload, self.recorder, resume)
        self.pool = start_pool(self.config, self.workload, self.buffer, self.counters.episodes)
        try:
            self._selfplay()
            if self.stop.requested:
                # SIGKILL may follow a SIGTERM within seconds (`ray job stop` waits 3 s unless the head
                # was started with RAY_JOB_STOP_WAIT_TIME_S): the checkpoint comes before anything else.
                self._final_checkpoint()
        finally:
            self.pool.shutdown()  # batches under way are dropped: the budget is a hard limit
        if not self.stop.requested:
            self._validate_if_it_fits(time.monotonic(), final=True)
            self._final_checkpoint()
        return self._result()

    def _final_checkpoint(self) -> None:
        self._charts()  # the curves end at the final step
        self._checkpoint()

    def _selfplay(self) -> None:
        """Self-play and learn until a stop signal, the last learner step, or the end of the budget less
        what the final validation needs."""
        c, learner = self.counters, self.learner
        weights = [ray.put(jax.device_get(learner.params))]
        self.pool.submit_all(weights, c.version)
        start, base_seconds = time.monotonic(), c.seconds
        nodes = NodeWatch.start()
        while (
            not self.stop.requested
            and self._selfplay_time_left()
            and not self.pacing.reached_max(learner.step)
        ):
            weights = self._turn(weights)
            c.seconds = base_seconds + time.monotonic() - start
            nodes.check(time.monotonic(), self.pool)
            self._periodic(time.monotonic())
        c.seconds = base_seconds + time.monotonic() - start

    def _selfplay_time_left(self) -> bool:
        """Whether the budget has time left once the final validation's share is kept for it."""
        reserve = final_reserve(self._validation_estimate(), self.config)
        return not self.schedule.over(time.monotonic() + reserve)

    def _turn(self, weights: list[ray.ObjectRef]) -> list[ray.ObjectRef]:
        """Collect the finished batches (waiting up to 1 s for one when the learner may not step), hand
        their actors the current weights, then take a learner step if pacing allows; returns the weights
        to hand out next."""
        c, learner, pool = self.counters, self.learner, self.pool
        oldest = pool.oldest_version()
        can_learn = self.pacing.can_learn(
            step=learner.step,
            transitions=c.transitions,
            version=c.version,
            oldest_version=c.version if oldest is None else oldest,
        )
        timeout = 0.0 if can_learn else min(1.0, max(0.0, self.schedule.deadline - time.monotonic()))
        for actor, stats in pool.collect(timeout, weights):
            self._count(stats)
            pool.submit(actor, weights, c.version)
        if can_learn and self._learn():
            return [ray.put(jax.device_get(learner.params))]
        return weights

    def _result(self) -> TrainResult:
        c, seconds = self.counters, max(self.counters.seconds, 1e-9)
        return TrainResult(
            steps=self.learner.step,
            episodes=c.episodes,
            selfplay_success_rate=c.successes / max(c.episodes, 1),
            validation=self.validator.last,
            best_success_rate=c.best_rate,
            seconds=time.monotonic() - self.began,
            episodes_per_sec=c.episodes / seconds,
            simulations_per_sec=c.simulations / seconds,
            actors=self.pool.layout.actors,
            logdir=str(self.recorder.logdir),
            interrupted=self.stop.requested,
            stop_signal=self.stop.signum,
            peak_rss_mb=dict(self.progress.memory),
        )

    def _count(self, stats) -> None:
        c, p = self.counters, self.progress
        c.add(stats)
        p.lag = c.version - stats.version
        p.batch_seconds = min(stats.seconds, p.batch_seconds or stats.seconds)
        p.memory["actor"] = max(p.memory["actor"], stats.peak_rss_mb)
        c.transitions = stats.buffer.added
        p.buffer_successes = stats.buffer.successes
        p.memory["buffer"] = stats.buffer.peak_rss_mb

    def _learn(self) -> bool:
        """One learner step; True when it published a new weights version."""
        learner, c = self.learner, self.counters
        sample: dict = ray.get(
            self.buffer.sample.remote(
                self.config.learner.batch_size, learner.next_seed(), self.config.success_fraction
            )
        )
        losses = learner.update(sample)
        if learner.step % 10 == 0 or learner.step == 1:
            policy, value = losses["policy"], losses["value"]
            scalars = {"losses/policy": policy, "losses/value": value, "losses/total": policy + value}
            self.recorder.scalars(scalars, learner.step)
        if learner.step % self.config.publish_every == 0:
            c.version += 1
            return True
        return False

    def _periodic(self, now: float) -> None:
        step, schedule = self.learner.step, self.schedule
        if schedule.report_due(now):
            self._charts()
            self._report()
        if schedule.checkpoint_due(now, step):
            self._checkpoint()
            schedule.checkpointed(time.monotonic())
        if schedule.validation_due(now) and not self.stop.requested:
            self._validate_if_it_fits(now, final=False)
            schedule.validated(time.monotonic())

    def _report(self) -> None:
        c, p, last = self.counters, self.progress, self.validator.last
        log.info(
            "step %d | episodes %d | self-play success %.1f%% | validation %s | lag %d | "
            "peak MiB driver %.0f buffer %.0f actor %.0f | %.0f s",
            self.learner.step,
            c.episodes,
            100 * c.successes / max(c.episodes, 1),
            "-" if last is None else f"{100 * last.success_rate:.1f}%",
            p.lag,
            p.memory["driver"],
            p.memory["buffer"],
            p.memory["actor"],
            c.seconds,
        )

    def _charts(self) -> None:
        self.progress.memory["driver"] = peak_rss_mb()
        values = _chart_values(self.counters, self.progress, self.learner.step, self.config.buffer_capacity)
        self.recorder.scalars(values, self.learner.step)

    def _checkpoint(self) -> None:
        ray.get(self.buffer.snapshot.remote(str(self.recorder.logdir / "replay.npz")))
        last = self.validator.last
        state = self.learner.state()
        self.recorder.checkpoint(
            self.learner.step, state, None if last is None else last.to_json(), self.counters
        )

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


def _chart_values(c: Counters, p: _Progress, step: int, capacity: int) -> dict[str, float]:
    """The run's TensorBoard charts: throughput, policy lag, self-play success, buffer and memory."""
    seconds = max(c.seconds, 1e-9)
    return {
        "charts/episodes_per_sec": c.episodes / seconds,
        "charts/simulations_per_sec": c.simulations / seconds,
        "charts/learner_steps_per_sec": step / seconds,
        "charts/policy_lag": p.lag,
        "charts/selfplay_success_rate": c.successes / max(c.episodes, 1),
        "buffer/size": min(c.transitions, capacity),
        "buffer/success_transitions": p.buffer_successes,
        **{f"memory/{kind}_peak_mb": mb for kind, mb in p.memory.items()},
    }
