"""`rllock bench selfplay`: self-play throughput for actor counts with the learner idle, and where the
time goes (sampling, network, host), from the actors' own timers."""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from typing import Any

import jax
import ray

from rllock.config import MCTSConfig, NetConfig, SelfPlayConfig
from rllock.core.env import Task
from rllock.learner.replay import ReplayBuffer
from rllock.orchestration.pool import ActorPool, Layout, on_driver_node, plan_layout, start_ray
from rllock.search.base import TimeSplit
from rllock.search.network import init_params
from rllock.search.workload import SingleTask

log = logging.getLogger(__name__)


def start_buffer(workload: SingleTask, mcts: MCTSConfig, capacity: int = 10_000) -> Any:
    """A replay buffer actor for `workload`, on this process's node, as training places it. Its handle is
    Any: Ray types an ActorHandle's methods as Never, and mypy checks nothing after a call of one."""
    layout = workload.buffer_layout("rl-lock", mcts)
    buffer: Any = (
        ray.remote(num_cpus=0)(ReplayBuffer)
        .options(scheduling_strategy=on_driver_node())
        .remote(capacity, *layout.shape, *layout.dtypes)
    )
    return buffer


def drain(pool: ActorPool) -> None:
    while pool.alive():
        pool.collect(timeout=5.0)


def timed_window(
    pool: ActorPool, buffer: Any, weights: list, seconds: float, learn: Callable[[], None] | None = None
) -> dict:
    """Self-play throughput over a window of `seconds`: batches are handed out until it ends, and those
    under way then count (the window ends with them). `learn`, when given, runs between collections, as
    the learner does in training; its calls are counted. The bytes per episode are the episodes' arrays
    as `buffer` received them."""
    episodes = simulations = decisions = steps = 0
    received_before = ray.get(buffer.counts.remote()).received_bytes
    times = TimeSplit()
    busy = 0.0
    start = time.perf_counter()
    pool.submit_all(weights, 0)
    while pool.alive():
        window_open = time.perf_counter() - start < seconds
        for actor, stats in pool.collect(timeout=0.0 if learn and window_open else 1.0):
            episodes += stats.episodes
            simulations += stats.simulations
            decisions += stats.decisions
            busy += stats.seconds
            times.add(stats.times)
            if time.perf_counter() - start < seconds:
                pool.submit(actor, weights, 0)
        if learn is not None and window_open:
            learn()
            steps += 1
    elapsed = time.perf_counter() - start
    sent = ray.get(buffer.counts.remote()).received_bytes - received_before
    sims = max(simulations, 1)
    return {
        "episodes": episodes,
        "decisions": decisions,
        "seconds": elapsed,
        "episodes_per_sec": episodes / elapsed,
        "episodes_per_hour": 3600 * episodes / elapsed,
        "simulations_per_sec": simulations / elapsed,
        "learner_steps_per_sec": steps / elapsed,
        "bytes_per_episode": sent / max(episodes, 1),
        "ms_per_simulation": {
            "sampling": 1000 * times.sampling / sims,
            "network": 1000 * times.network / sims,
            "host": 1000 * times.host / sims,
            "other": 1000 * max(0.0, busy - times.sampling - times.network - times.host) / sims,
        },
    }


def _measure(
    task: Task, net: NetConfig, mcts: MCTSConfig, layout: Layout, params_ref, seconds: float
) -> dict:
    workload = SingleTask.of(task, net.canvas_side())
    buffer = start_buffer(workload, mcts)
    pool = ActorPool(workload, net, mcts, "rl-lock", layout, 100, buffer)
    weights = [params_ref]
    pool.submit_all(weights, 0)  # compile and warm up outside the timed window
    drain(pool)
    row = timed_window(pool, buffer, weights, seconds)
    pool.shutdown()
    ray.kill(buffer)
    del row["learner_steps_per_sec"]
    return {
        "actors": layout.actors,
        "mode": layout.mode,
        "episodes_per_batch": layout.episodes,
        "threads_per_actor": layout.threads,
        "groups_per_actor": layout.groups,
        **row,
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
