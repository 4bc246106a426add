"""`rllock bench selfplay`: self-play throughput for actor counts with the learner idle, and where the
time goes (sampling, network, host), from the actors' own timers."""

from __future__ import annotations

import dataclasses
import logging
import time

import jax
import ray
from ray.actor import ActorHandle

from actors.selfplay import TaskSpec
from learner.replay import ReplayBuffer
from orchestration.pool import ActorPool, Layout, plan_layout, start_ray
from rllock.config import MCTSConfig, NetConfig, SelfPlayConfig
from rllock.core.env import Task, compact_dtypes
from rllock.search.base import TimeSplit
from rllock.search.network import init_params

log = logging.getLogger(__name__)


def _measure(
    task: Task, net: NetConfig, mcts: MCTSConfig, layout: Layout, params_ref, seconds: float
) -> dict:
    # Ray types .remote() as ActorHandle | type[ReplayBuffer] (for its method typing); it is a handle.
    buffer: ActorHandle = ray.remote(num_cpus=0)(ReplayBuffer).remote(  # type: ignore[assignment]
        10_000, task.size, mcts.candidates, task.piece_size, *compact_dtypes(task)
    )
    pool = ActorPool(TaskSpec.of(task), net, mcts, "rl-lock", layout, 100, buffer)
    weights = [params_ref]
    pool.submit_all(weights, 0)  # compile and warm up outside the timed window
    while pool.alive():
        pool.collect(timeout=5.0)
    episodes = simulations = decisions = 0
    times = TimeSplit()
    busy = 0.0
    start = time.perf_counter()
    pool.submit_all(weights, 0)
    while pool.alive():
        for actor, stats in pool.collect(timeout=1.0):
            episodes += stats.episodes
            simulations += stats.simulations
            decisions += stats.decisions
            busy += stats.seconds
            times.add(stats.times)
            if time.perf_counter() - start < seconds:  # batches under way count: the window ends with them
                pool.submit(actor, weights, 0)
    elapsed = time.perf_counter() - start
    pool.shutdown()
    ray.kill(buffer)
    sims = max(simulations, 1)
    return {
        "actors": layout.actors,
        "mode": layout.mode,
        "episodes_per_batch": layout.episodes,
        "threads_per_actor": layout.threads,
        "groups_per_actor": layout.groups,
        "episodes": episodes,
        "decisions": decisions,
        "seconds": elapsed,
        "episodes_per_sec": episodes / elapsed,
        "episodes_per_hour": 3600 * episodes / elapsed,
        "simulations_per_sec": simulations / elapsed,
        "ms_per_simulation": {
            "sampling": 1000 * times.sampling / sims,
            "network": 1000 * times.network / sims,
            "host": 1000 * times.host / sims,
            "other": 1000 * max(0.0, busy - times.sampling - times.network - times.host) / sims,
        },
    }


def bench_selfplay(
    task: Task, net: NetConfig, mcts: MCTSConfig, selfplay: SelfPlayConfig, counts: list[int], seconds: float
) -> list[dict]:
    """One row per actor count; `net` has a concrete canvas. Ray's CPUs are all free (no learner)."""
    started = start_ray(None)
    try:
        params_ref = ray.put(jax.device_get(init_params(net, jax.random.PRNGKey(0))))
        resources = ray.cluster_resources()
        rows = []
        for n in counts:
            layout = plan_layout(
                dataclasses.replace(selfplay, actors=n),
                cpus=resources.get("CPU", 1),
                gpus=resources.get("GPU", 0),
                reserved_cpus=0,
            )
            rows.append(_measure(task, net, mcts, layout, params_ref, seconds))
            log.info("%d actor(s): %.3f episodes/s", n, rows[-1]["episodes_per_sec"])
        return rows
    finally:
        if started:
            ray.shutdown()
