"""The actor-learner loop of both trainers (`rllock train`, `rllock train-guide`), the whole system in one
place: actors feed the replay buffer, the learner samples it, and new weights go back to the actors.

Each actor has exactly one call in flight, played with the weights version it was handed; the loop
collects the finished calls (their reports counted into `Counters`), hands their actors the newest
weights, and takes a learner step when `Pacing` allows: data enough, under the replay ratio, and (where
the trainer bounds it) no call in flight too many versions behind. Every `publish_every` steps the weights
are a new version. Checkpoints (the replay buffer's snapshot with them) come as `Schedule` says, and a
final one unless the last one already holds everything. `--minutes` is a hard budget: calls under way at
its end are dropped. What the trainers differ in is built by `rllock.orchestration.builder` (the actors, the
learner, the buffer and the rules from their config); what each watches beside this loop (validations,
judgements, its log lines and charts) is its `Monitor`.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Generic, Protocol, TypeVar

import numpy as np

from rllock.orchestration.pacing import Pacing, Schedule
from rllock.orchestration.recorder import Counters, Recorder
from rllock.orchestration.stopping import StopRequest

LOSSES_EVERY = 10  # learner steps between the losses written to TensorBoard (and the first step's)


class Learning(Protocol):
    """A learner (`rllock.learner.learner.Learner`, `rllock.learner.guide_learner.GuideLearner`)."""

    step: int

    def next_seed(self) -> int: ...

    def learn(self, sample: dict[str, np.ndarray]) -> dict[str, float]:
        """One step on a replay sample; its losses by TensorBoard tag."""
        ...

    def state(self) -> dict:
        """Everything a resume needs, as one pytree (what a checkpoint saves)."""
        ...

    @property
    def weights(self) -> dict:
        """The parameters the actors act with."""
        ...


class Replay(Protocol):
    """A replay buffer, as the loop reaches it (a Ray actor's, or one in this process)."""

    def sample(self, batch: int, seed: int) -> dict[str, np.ndarray]: ...

    def snapshot(self) -> None:
        """Write the buffer into the run's folder, beside a checkpoint."""
        ...


class Actors(Protocol):
    """A trainer's actors (`rllock.orchestration.pool`), one call in flight each."""

    def publish(self, params: dict) -> list:
        """A weights version as the actors fetch it."""
        ...

    def start(self, weights: list, version: int) -> None: ...

    def collect(self, timeout: float, weights: list) -> Sequence[tuple[Any, Any]]:
        """(actor, report) of the calls finished within `timeout` seconds; an actor that failed for good
        is replaced, its replacement handed `weights`."""
        ...

    def submit(self, actor: Any, weights: list, version: int) -> None: ...

    def oldest_version(self) -> int | None:
        """The oldest weights version in flight, where the trainer bounds the policy lag."""
        ...

    def stop(self) -> None:
        """Drop the calls under way."""
        ...


class Monitor(Protocol):
    """What a trainer watches beside the loop's own work: each report, its periodic charts and log lines,
    its evaluations (a policy run's validations, a guide run's judgement of held-out nodes)."""

    def count(self, report: Any) -> None:
        """A report the counters have just added."""
        ...

    def periodic(self, now: float) -> None:
        """After each turn (and its checkpoint, when one was due): whatever else is due now."""
        ...

    def reserve(self) -> float:
        """Seconds the loop keeps at the end of the budget for `final`."""
        ...

    def score(self) -> dict | None:
        """The latest evaluation's score, which a checkpoint's metadata keeps (None: none)."""
        ...

    def checkpointed(self) -> None:
        """After each checkpoint."""
        ...

    def final(self, now: float, *, stopped: bool) -> None:
        """Before the final checkpoint (`stopped`: a signal ended the run, which must save at once)."""
        ...


@dataclass
class System:
    """A trainer as `rllock.orchestration.builder` built it: what the loop runs."""

    learner: Learning
    buffer: Replay
    actors: Actors
    counters: Counters
    recorder: Recorder
    pacing: Pacing
    schedule: Schedule
    publish_every: int | None  # learner steps between weights versions (None: no actors to hand them)
    resumed: bool


M = TypeVar("M", bound=Monitor)


class Loop(Generic[M]):
    """The loop over a built trainer; `run` returns once the budget, the step limit or a stop signal
    (`stop`) ends it, its final checkpoint saved."""

    def __init__(self, system: System, monitor: M, stop: StopRequest):
        self.system, self.monitor, self.stop = system, monitor, stop
        self.reports = 0  # reports counted by this process
        # What the last checkpoint holds: a resumed run's is where it starts.
        self.saved = self._marker() if system.resumed else None

    def run(self) -> None:
        s = self.system
        weights = s.actors.publish(s.learner.weights)
        s.actors.start(weights, s.counters.version)
        try:
            self._turns(weights)
            if self.stop.requested:
                # SIGKILL may follow a SIGTERM within seconds (`ray job stop` waits 3 s unless the head
                # was started with RAY_JOB_STOP_WAIT_TIME_S): the checkpoint comes before anything else.
                self._finish(stopped=True)
        finally:
            s.actors.stop()
        if not self.stop.requested:
            self._finish(stopped=False)

    def _turns(self, weights: list) -> None:
        """Turns until a stop signal, the last learner step, or the end of the budget less what the
        monitor keeps for its final work; checkpoints and the monitor's periodic work between them."""
        s, c = self.system, self.system.counters
        start, base_seconds = time.monotonic(), c.seconds
        while not self.stop.requested and self._time_left() and not s.pacing.reached_max(s.learner.step):
            weights = self._turn(weights)
            now = time.monotonic()
            c.seconds = base_seconds + now - start
            if s.schedule.checkpoint_due(now, s.learner.step):
                self._checkpoint()
                s.schedule.checkpointed(time.monotonic())
            if not self.stop.requested:
                self.monitor.periodic(now)
        c.seconds = base_seconds + time.monotonic() - start

    def _time_left(self) -> bool:
        return not self.system.schedule.over(time.monotonic() + self.monitor.reserve())

    def _turn(self, weights: list) -> list:
        """Collect the finished calls (waiting up to 1 s for one when the learner may not step), hand their
        actors the current weights, then take a learner step if pacing allows; returns the weights to
        hand out next."""
        s, c = self.system, self.system.counters
        oldest = s.actors.oldest_version()
        can_learn = s.pacing.can_learn(
            step=s.learner.step,
            transitions=c.produced,
            version=c.version,
            oldest_version=c.version if oldest is None else oldest,
        )
        timeout = 0.0 if can_learn else min(1.0, max(0.0, s.schedule.deadline - time.monotonic()))
        for actor, report in s.actors.collect(timeout, weights):
            c.add(report)
            self.reports += 1
            self.monitor.count(report)
            s.actors.submit(actor, weights, c.version)
        if can_learn and self._learn():
            return s.actors.publish(s.learner.weights)
        return weights

    def _learn(self) -> bool:
        """One learner step; True when it made a new weights version."""
        s = self.system
        losses = s.learner.learn(s.buffer.sample(s.pacing.batch_size, s.learner.next_seed()))
        step = s.learner.step
        if step % LOSSES_EVERY == 0 or step == 1:
            s.recorder.scalars(losses, step)
        if s.publish_every is None or step % s.publish_every:
            return False
        s.counters.version += 1
        return True

    def _checkpoint(self) -> None:
        s = self.system
        s.buffer.snapshot()
        s.recorder.checkpoint(s.learner.step, s.learner.state(), self.monitor.score(), s.counters)
        self.monitor.checkpointed()
        s.recorder.flush()
        self.saved = self._marker()

    def _finish(self, *, stopped: bool) -> None:
        self.monitor.final(time.monotonic(), stopped=stopped)
        if self._marker() != self.saved:
            self._checkpoint()

    def _marker(self) -> tuple[int, int, dict | None]:
        """What a checkpoint now would hold that the last one may not: the learner step, the reports
        counted, the latest score."""
        return self.system.learner.step, self.reports, self.monitor.score()
