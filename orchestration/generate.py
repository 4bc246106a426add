"""`rllock generate --actors N [--address HOST:PORT]`: the inference protocol's rounds spread over N Ray
actors of one CPU core each, locally or on a cluster. The driver hands out rounds (seeded as in-process
generation, see `rllock.search.inference`), deduplicates the finished ones, verifies and writes them. The
parameters travel as host arrays, so a checkpoint trained on any device runs there."""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from pathlib import Path

import jax
import ray

from rllock.actors.selfplay import actor_env
from rllock.files.assembly import PictureWriter
from rllock.orchestration.pool import Calls, start_ray
from rllock.search.inference import Collector, GenerateResult, Policy, play_round, searchers_for

log = logging.getLogger(__name__)


@ray.remote
class GenerateActor:
    def __init__(self, policy: Policy, batch: int):
        self.policy = policy
        self.searchers = searchers_for(policy, batch, 1)  # one core each

    def play(self, seed: int, round_: int):
        start = time.perf_counter()
        episodes = play_round(self.searchers, self.policy, seed, round_)
        return episodes, time.perf_counter() - start


def generate_on_ray(
    policy: Policy,
    *,
    actors: int,
    address: str | None,
    count: int,
    batch: int,
    time_limit: float,
    seed: int,
    out: Path | None = None,
    picture: PictureWriter | None = None,
    progress: bool = True,
    stop: Callable[[], bool] = lambda: False,
) -> GenerateResult:
    """Like `rllock.search.inference.generate`, with rounds played by `actors` Ray actors (one core each);
    after `stop()` no round is handed out and those under way are dropped."""
    started = start_ray(address)
    try:
        host_policy = dataclasses.replace(policy, params=jax.device_get(policy.params))
        start = time.perf_counter()
        collector = Collector(
            policy, count=count, batch=batch, seed=seed, out=out, picture=picture, progress=progress
        )
        rounds = _Rounds(host_policy, batch, seed)
        rounds.play(actors, collector, stop, lambda: time.perf_counter() - start >= time_limit or stop())
        return collector.result(time.perf_counter() - start)
    finally:
        if started:
            ray.shutdown()


class _Rounds:
    """The protocol's rounds handed out to actors of one core each, one round in flight per actor. Ray
    restarts a dead actor process and retries its round; an actor that fails for good is replaced and
    its round played by the new one."""

    def __init__(self, policy: Policy, batch: int, seed: int):
        self.policy, self.batch, self.seed = policy, batch, seed
        self.options = dict(
            num_cpus=1, max_restarts=-1, max_task_retries=-1, runtime_env={"env_vars": actor_env(1)}
        )
        self.calls = Calls()
        self.next_round = 0

    def _actor(self):
        # mypy skips class decorators: @ray.remote made GenerateActor an ActorClass, which has .options.
        return GenerateActor.options(**self.options).remote(self.policy, self.batch)  # type: ignore[attr-defined]

    def _hand(self, actor, round_: int | None = None) -> None:
        """Hand `actor` a round: `round_`, or the next one."""
        if round_ is None:
            round_, self.next_round = self.next_round, self.next_round + 1
        self.calls.submit(actor, actor.play.remote(self.seed, round_), round_)

    def play(
        self, actors: int, collector: Collector, stop: Callable[[], bool], over: Callable[[], bool]
    ) -> None:
        """Rounds until `collector` is done or `stop()`; after `over()` no round is handed out and those
        under way finish. Then the actors are stopped."""
        pool = [self._actor() for _ in range(actors)]
        for actor in pool:
            self._hand(actor)
        while self.calls and not collector.done and not stop():
            done, failed = self.calls.wait(None)
            for actor, round_, why in failed:
                log.error("generation actor failed for good (%s); a new actor plays round %d", why, round_)
                pool[pool.index(actor)] = actor = self._actor()
                self._hand(actor, round_)
            for actor, _, (episodes, seconds) in done:
                collector.take(episodes, seconds)
                if not collector.done and not over():
                    self._hand(actor)
        self.calls.cancel_all()  # rounds still under way are not needed
        for actor in pool:
            ray.kill(actor)
