"""`rllock generate --actors N [--address HOST:PORT]`: the inference protocol's rounds spread over N Ray
actors of one CPU core each, locally or on a cluster. The driver hands out rounds (seeded as in-process
generation, see `rllock.search.inference`), deduplicates the finished ones, verifies and writes them. The
parameters travel as host arrays, so a checkpoint trained on any device runs there."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path

import jax
import ray

from actors.selfplay import actor_env
from orchestration.pool import start_ray
from rllock.files.assembly import PictureWriter
from rllock.search.inference import Collector, GenerateResult, Policy, play_round, searchers_for


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
        options = dict(num_cpus=1, runtime_env={"env_vars": actor_env(1)})
        # mypy skips class decorators: @ray.remote made GenerateActor an ActorClass, which has .options.
        pool = [
            GenerateActor.options(**options).remote(host_policy, batch)  # type: ignore[attr-defined]
            for _ in range(actors)
        ]
        start = time.perf_counter()
        collector = Collector(
            policy, count=count, batch=batch, seed=seed, out=out, picture=picture, progress=progress
        )
        inflight = {a.play.remote(seed, r): a for r, a in enumerate(pool)}
        next_round = len(pool)
        while inflight and not collector.done and not stop():
            ready, _ = ray.wait(list(inflight), num_returns=1)
            actor = inflight.pop(ready[0])
            episodes, seconds = ray.get(ready[0])
            collector.take(episodes, seconds)
            if not collector.done and time.perf_counter() - start < time_limit and not stop():
                inflight[actor.play.remote(seed, next_round)] = actor
                next_round += 1
        for actor in pool:  # rounds still under way are not needed
            ray.kill(actor)
        return collector.result(time.perf_counter() - start)
    finally:
        if started:
            ray.shutdown()
