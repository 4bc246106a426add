"""The one actor-learner loop of both trainers, on stand-in parts (no Ray, no JAX), and the counters every
checkpoint keeps."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

from rllock.actors.guide_actor import SearchTotals
from rllock.actors.selfplay import PlayTotals
from rllock.orchestration.loop import Loop, System
from rllock.orchestration.pacing import Pacing, Schedule
from rllock.orchestration.recorder import Counters, totals_of
from rllock.orchestration.stopping import StopRequest


def test_counters_keep_the_keys_checkpoints_have_always_held_and_read_them_back():
    play = Counters(PlayTotals(3, 1, 96, 40), seconds=5.0, version=2, best=(0.5, 0.75))
    doc = play.to_json()
    assert set(doc) == {
        "episodes",
        "successes",
        "simulations",
        "transitions",
        "seconds",
        "version",
        "best_rate",
        "best_return",
    }
    back = Counters.of(doc, totals_of(PlayTotals, doc), validates=True)
    assert back == play and back.produced == 40
    search = Counters(SearchTotals(4, 2, 2, 1, 30, {"cube4:7": 8}), seconds=1.0, version=1)
    doc = search.to_json()
    saved = ("searches", "solved", "guided", "guided_solved", "states", "edge", "seconds", "version")
    assert set(doc) == set(saved)
    assert Counters.of(doc, totals_of(SearchTotals, doc)) == search
    # A checkpoint from before a field: its default.
    assert totals_of(SearchTotals, {"searches": 2}) == SearchTotals(searches=2)
    assert Counters().to_json() == {"seconds": 0.0, "version": 0}


@dataclass
class Report:
    version: int
    items: int = 4


@dataclass
class Totals:
    reports: int = 0
    items: int = 0

    def add(self, report: Report) -> None:
        self.reports += 1
        self.items += report.items

    @property
    def produced(self) -> int:
        return self.items


class Learner:
    def __init__(self, step: int = 0):
        self.step, self.seeds = step, 0

    def next_seed(self) -> int:
        self.seeds += 1
        return self.seeds

    def learn(self, sample: dict) -> dict[str, float]:
        self.step += 1
        return {"losses/x": float(self.step)}

    def state(self) -> dict:
        return {"step": self.step}

    @property
    def weights(self) -> dict:
        return {"step": self.step}


@dataclass
class Buffer:
    samples: int = 0
    snapshots: int = 0

    def sample(self, batch: int, seed: int) -> dict:
        self.samples += 1
        return {}

    def snapshot(self) -> None:
        self.snapshots += 1


@dataclass
class Actors:
    """Two actors whose calls finish at once; `events` is what happened, in order."""

    events: list = field(default_factory=list)
    inflight: dict = field(default_factory=dict)

    def publish(self, params: dict) -> list:
        return [params["step"]]

    def start(self, weights: list, version: int) -> None:
        for actor in ("a", "b"):
            self.submit(actor, weights, version)

    def collect(self, timeout: float, weights: list) -> list:
        done = [(actor, Report(version)) for actor, (_, version) in self.inflight.items()]
        self.inflight = {}
        return done

    def submit(self, actor: str, weights: list, version: int) -> None:
        self.inflight[actor] = (weights, version)
        self.events.append(("submit", actor, weights[0], version))

    def oldest_version(self) -> int | None:
        return min((v for _, v in self.inflight.values()), default=None)

    def stop(self) -> None:
        self.events.append(("stop",))


@dataclass
class Recorder:
    events: list
    scalars_at: list = field(default_factory=list)

    def scalars(self, values: dict, step: int) -> None:
        self.scalars_at.append(step)

    def checkpoint(self, step: int, state: dict, validation: dict | None, counters: Counters) -> None:
        self.events.append(("checkpoint", step, dict(counters.to_json(), seconds=0)))

    def flush(self) -> None:
        pass


class Monitor:
    def __init__(self, stop: StopRequest | None = None, stop_at: int | None = None):
        self.counted, self.stop, self.stop_at = 0, stop, stop_at

    def count(self, report: Report) -> None:
        self.counted += 1
        if self.stop is not None and self.counted == self.stop_at:
            self.stop.handle(15, None)  # as SIGTERM would

    def periodic(self, now: float) -> None:
        pass

    def reserve(self) -> float:
        return 0.0

    def score(self) -> dict | None:
        return None

    def checkpointed(self) -> None:
        pass

    def final(self, now: float, *, stopped: bool) -> None:
        pass


def _system(steps: int, *, learner: Learner | None = None, lag: int | None = 4, resumed: bool = False):
    actors = Actors()
    recorder = Recorder(actors.events)
    totals = Totals()
    system = System(
        learner=learner or Learner(),
        buffer=Buffer(),
        actors=actors,
        counters=Counters(totals),
        recorder=recorder,  # type: ignore[arg-type]
        pacing=Pacing(warmup=8, batch_size=2, replay_ratio=1.0, max_policy_lag=lag, max_learner_steps=steps),
        schedule=Schedule.of(time.monotonic(), minutes=5, checkpoint_minutes=10, reserve_s=0.0),
        publish_every=3,
        resumed=resumed,
    )
    return system, actors, recorder


def test_the_loop_learns_as_pacing_allows_publishes_versions_and_checkpoints_at_the_first_step_and_the_end():
    system, actors, recorder = _system(12)
    Loop(system, Monitor(), StopRequest()).run()
    assert system.learner.step == 12 and system.counters.version == 4
    # No step before the warmup's 8 items (the first turn's two reports), then one a turn: under the
    # replay ratio (1, batch 2: 2 items a step), as the turns bring 8 items each.
    assert system.counters.totals.reports == 2 * 13
    checkpoints = [e for e in actors.events if e[0] == "checkpoint"]
    assert [c[1] for c in checkpoints] == [1, 12]  # the first step's, then the final one
    totals = system.counters.totals
    assert checkpoints[-1][2] == {
        "reports": totals.reports,
        "items": totals.items,
        "seconds": 0,
        "version": 4,
    }
    # The budget is a hard limit: calls under way are dropped before the final checkpoint.
    assert actors.events[-2] == ("stop",) and system.buffer.snapshots == 2
    # Each actor is handed the newest weights and version after each call.
    versions = [e[3] for e in actors.events if e[0] == "submit"]
    assert versions == sorted(versions) and set(versions) == {0, 1, 2, 3}  # 4: made by the last step
    assert recorder.scalars_at == [1, 10]


def test_a_stop_signal_saves_a_checkpoint_before_the_actors_stop():
    system, actors, _ = _system(None)  # type: ignore[arg-type]
    stop = StopRequest()
    Loop(system, Monitor(stop, stop_at=6), stop).run()
    assert stop.requested and actors.events[-2][0] == "checkpoint" and actors.events[-1] == ("stop",)
    assert actors.events[-2][1] == system.learner.step > 0


def test_a_resumed_run_with_nothing_new_saves_no_checkpoint():
    system, actors, _ = _system(5, learner=Learner(step=5), resumed=True)
    Loop(system, Monitor(), StopRequest()).run()
    assert not [e for e in actors.events if e[0] == "checkpoint"] and system.buffer.snapshots == 0


def test_without_a_lag_limit_or_a_replay_ratio_the_learner_steps_at_every_turn():
    pacing = Pacing(1, 64, math.inf, None, None)
    assert pacing.can_learn(step=10**6, transitions=1, version=9, oldest_version=0)
    assert not pacing.can_learn(step=0, transitions=0, version=0, oldest_version=0)
