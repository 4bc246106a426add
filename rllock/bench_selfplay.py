"""`rllock bench selfplay`: self-play throughput of N Ray actors with the learner idle."""

from __future__ import annotations

import argparse
import logging
import os
import time

import jax
import ray

from actors.selfplay import ACTOR_ENV, SelfPlayActor, SelfPlayConfig, TaskSpec
from learner.replay import ReplayBuffer
from rllock.env import compact_dtypes, make_task
from rllock.mcts import MCTSConfig
from rllock.network import NetConfig, check_fits, init_params

log = logging.getLogger(__name__)


def _measure(spec: TaskSpec, config: SelfPlayConfig, params_ref, actors: int, seconds: float) -> dict:
    task = spec.make()
    buffer = ray.remote(num_cpus=0)(ReplayBuffer).remote(10_000, task.size, config.mcts.candidates,
                                                         task.piece_size, *compact_dtypes(task))
    pool = [SelfPlayActor.options(runtime_env={"env_vars": ACTOR_ENV}).remote(spec, config, 100 + i, buffer)
            for i in range(actors)]
    weights = [params_ref]
    ray.get([a.run.remote(weights, 0) for a in pool])  # compile and warm up outside the timed window
    episodes = simulations = 0
    start = time.perf_counter()
    inflight = {a.run.remote(weights, 0): a for a in pool}
    while time.perf_counter() - start < seconds:
        ready, _ = ray.wait(list(inflight), num_returns=1)
        for ref in ready:
            actor = inflight.pop(ref)
            stats = ray.get(ref)
            episodes += stats.episodes
            simulations += stats.simulations
            inflight[actor.run.remote(weights, 0)] = actor
    finished = ray.get(list(inflight))  # batches under way count: the window ends when they do
    episodes += sum(s.episodes for s in finished)
    simulations += sum(s.simulations for s in finished)
    elapsed = time.perf_counter() - start
    for a in pool:
        ray.kill(a)
    ray.kill(buffer)
    return {"actors": actors, "episodes": episodes, "seconds": elapsed, "episodes_per_sec": episodes / elapsed,
            "simulations_per_sec": simulations / elapsed}


def bench_selfplay(args: argparse.Namespace, counts: list[int]) -> list[dict]:
    task = make_task(args.shape, args.pieces)
    net = NetConfig(canvas=args.canvas)
    check_fits(task, net)
    config = SelfPlayConfig(args.episodes_per_batch, MCTSConfig(simulations=args.simulations), net)
    started = not ray.is_initialized()
    if started:
        ray.init(num_cpus=max(max(counts), os.cpu_count() or 1), include_dashboard=False,
                 logging_level=logging.WARNING)
    try:
        params_ref = ray.put(jax.device_get(init_params(net, jax.random.PRNGKey(0))))
        rows = []
        for n in counts:
            rows.append(_measure(TaskSpec.of(task), config, params_ref, n, args.seconds))
            log.info("%d actor(s): %.3f episodes/s", n, rows[-1]["episodes_per_sec"])
        return rows
    finally:
        if started:
            ray.shutdown()
