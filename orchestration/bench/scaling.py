"""`rllock bench scaling`: how self-play and the learner scale with actors, and what spreading the same
cores over several Ray nodes costs.

For each node count and each actor count, a Ray cluster is started on this machine: one node holds every
core, or k > 1 nodes are a head without CPUs and k - 1 worker nodes that split the cores, each with its
own raylet and object store, all on 127.0.0.1 (`ray.cluster_utils.Cluster`). The actors play for a window
while the learner in this process steps on replay samples, as in training, which gives episodes and
learner steps per second, and the bytes per episode pushed through the object store. With the actors
idle, every actor then fetches a new weights version: the broadcast latency (median), beside the round
trip of an empty call. Last, the learner alone: steps per second on each JAX platform there is (the GPU
against the CPU on a workstation)."""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import statistics
import tempfile
import time
import warnings
from collections.abc import Iterator
from dataclasses import asdict, dataclass, replace

import jax
import numpy as np
import ray
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

from rllock.config import LearnerConfig, MCTSConfig, NetConfig, SelfPlayConfig
from rllock.core.env import make_task
from rllock.learner.learner import Learner
from rllock.orchestration.bench.selfplay import drain, start_buffer, timed_window
from rllock.orchestration.pool import ActorPool, largest_node_cpus, plan_layout
from rllock.search.network import fit_canvas
from rllock.search.workload import SingleTask

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ScalingPlan:
    shape: str
    pieces: int
    simulations: int
    episodes_per_batch: int
    actors: tuple[int, ...]
    nodes: tuple[int, ...]
    seconds: float  # each timed window
    learner_steps: int  # timed steps of the learner alone, per platform
    batch_size: int = LearnerConfig().batch_size
    broadcasts: int = 5
    features: tuple[int, ...] = NetConfig().features  # the network's width per level, as `train` has it


PRESETS = {
    # Sized for 2 cores: 1 and 2 actors, on one node and on three, in minutes.
    "small": ScalingPlan("cube4", 7, 64, 4, actors=(1, 2), nodes=(1, 3), seconds=20, learner_steps=30),
    # What a 16-core GPU workstation should report, in under 8 minutes there: the paper's search (256
    # simulations) on 6^3 K=25 with 1 to 15 actors (one core stays with the learner), 2 episodes a batch
    # so that a window holds several batches, and the learner on the GPU against the CPU.
    "workstation": ScalingPlan(
        "cube6", 25, MCTSConfig().simulations, 2, (1, 4, 8, 15), nodes=(1,), seconds=40, learner_steps=50
    ),
}


def fit_to_machine(plan: ScalingPlan, cores: int) -> ScalingPlan:
    """The plan on a machine with `cores`: actor counts beyond the cores are dropped (the largest that
    fits is kept; the learner shares the cores with them, as in training), and so are node counts that
    would leave a worker node no core."""
    actors = tuple(sorted({min(n, cores) for n in plan.actors}))
    nodes = tuple(k for k in plan.nodes if k == 1 or k - 1 <= cores)
    return replace(plan, actors=actors, nodes=nodes or (1,))


@contextlib.contextmanager
def local_cluster(nodes: int, cores: int) -> Iterator[None]:
    """Ray on this machine with `cores` CPUs in all over `nodes` nodes, connected; torn down on exit.
    The caller sets RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0 before Ray is imported, which keeps every node
    on loopback."""
    from ray.cluster_utils import Cluster

    head_cpus = cores if nodes == 1 else 0  # several nodes: the cores are the workers'
    head = {"node_ip_address": "127.0.0.1", "include_dashboard": False, "num_cpus": head_cpus}
    folders: list[str] = []
    with warnings.catch_warnings():
        # JAX warns at every fork once it runs threads; Ray forks only to exec its node processes at once.
        warnings.filterwarnings("ignore", "os.fork", RuntimeWarning)
        cluster = Cluster(initialize_head=True, head_node_args=head)
        workers = nodes - 1
        for i in range(workers):
            share = cores // workers + (1 if i < cores % workers else 0)
            # A temporary folder per node, as on separate machines: nodes sharing one delete each
            # other's unpacked runtime environments.
            folders.append(tempfile.mkdtemp(prefix="rlnode", dir="/tmp"))
            cluster.add_node(num_cpus=share, node_ip_address="127.0.0.1", temp_dir=folders[-1])
    try:
        cluster.wait_for_nodes()
        ray.init(address=cluster.address, logging_level=logging.WARNING)
        try:
            yield
        finally:
            ray.shutdown()
    finally:
        cluster.shutdown()
        for folder in folders:
            shutil.rmtree(folder, ignore_errors=True)


@ray.remote(num_cpus=0)
class _Probe:
    """Stands beside a self-play actor on its node, to time what reaches that node (`_broadcast_ms`)."""

    def where(self) -> int:
        return os.getpid()

    def fetch(self, weights: list) -> int:
        """Fetch a weights version and nothing else; returns the parameters' bytes."""
        return sum(leaf.nbytes for leaf in jax.tree_util.tree_leaves(ray.get(weights[0])))


def _broadcast_ms(pool: ActorPool, params: dict, repeats: int) -> tuple[float, float]:
    """(median ms for a process on every actor's node to fetch a new weights version, median ms of an empty
    call), with the actors idle."""
    probes = [
        _Probe.options(scheduling_strategy=NodeAffinitySchedulingStrategy(node, soft=False)).remote()  # type: ignore[attr-defined]
        for _, node in pool.places.values()
    ]
    ray.get([p.where.remote() for p in probes])  # started before the clock does
    fetch, call = [], []
    for _ in range(repeats):
        start = time.perf_counter()
        ray.get([p.where.remote() for p in probes])
        call.append(time.perf_counter() - start)
        ref = ray.put(params)  # a new object each time: no node holds it yet
        start = time.perf_counter()
        ray.get([p.fetch.remote([ref]) for p in probes])
        fetch.append(time.perf_counter() - start)
    for probe in probes:
        ray.kill(probe)
    return 1000 * statistics.median(fetch), 1000 * statistics.median(call)


def _measure(
    workload: SingleTask, net: NetConfig, mcts: MCTSConfig, plan: ScalingPlan, actors: int, learner: Learner
) -> tuple[dict, dict]:
    """One row: `actors` actors on the cluster Ray is connected to, the learner stepping beside them.
    Returns (the row, a replay sample for the learner-alone timing)."""
    resources = ray.cluster_resources()
    layout = plan_layout(
        SelfPlayConfig(actors=actors, episodes_per_batch=plan.episodes_per_batch, evaluation="per-actor"),
        cpus=resources.get("CPU", 1),
        gpus=0,
        reserved_cpus=0,
        node_cpus=largest_node_cpus(),
    )
    buffer = start_buffer(workload, mcts)
    pool = ActorPool(workload, net, mcts, "rl-lock", layout, 100, buffer)
    try:
        params = jax.device_get(learner.params)
        weights = [ray.put(params)]
        pool.submit_all(weights, 0)  # compile and warm up outside the timed window
        drain(pool)
        sample = ray.get(buffer.sample.remote(plan.batch_size, 0))
        learner.update(sample)  # compiled outside the window too

        def learn() -> None:
            learner.update(sample)

        row = timed_window(pool, buffer, weights, plan.seconds, learn)
        broadcast, call = _broadcast_ms(pool, params, plan.broadcasts)
        nodes = len(pool.nodes_in_use())
    finally:
        pool.shutdown()
        ray.kill(buffer)
    keep = ("episodes", "seconds", "episodes_per_sec", "learner_steps_per_sec", "bytes_per_episode")
    return {
        "actors": actors,
        "actor_nodes": nodes,
        "cpus_per_actor": layout.cpus,
        **{k: row[k] for k in keep},
        "broadcast_ms": broadcast,
        "call_ms": call,
        "param_bytes": int(sum(np.asarray(x).nbytes for x in jax.tree_util.tree_leaves(params))),
    }, sample


def learner_alone(workload: SingleTask, net: NetConfig, plan: ScalingPlan, sample: dict) -> dict[str, float]:
    """Learner steps per second on each JAX platform present, the machine otherwise idle."""
    rates = {}
    platforms = ["cpu"] + [p for p in ("gpu", "tpu") if _has(p)]
    for platform in platforms:
        with jax.default_device(jax.devices(platform)[0]):
            learner = Learner(workload, net, LearnerConfig(batch_size=plan.batch_size), jax.random.PRNGKey(0))
            learner.update(sample)  # compile
            start = time.perf_counter()
            for _ in range(plan.learner_steps):
                learner.update(sample)
            rates[platform] = plan.learner_steps / (time.perf_counter() - start)
        log.info("learner alone on %s: %.1f steps/s", platform, rates[platform])
    return rates


def _has(platform: str) -> bool:
    try:
        return bool(jax.devices(platform))
    except RuntimeError:
        return False


def bench_scaling(plan: ScalingPlan, cores: int | None = None) -> dict:
    """Every row of `plan` (fitted to this machine's cores), then the learner alone."""
    cores = cores or os.cpu_count() or 1
    plan = fit_to_machine(plan, cores)
    task = make_task(plan.shape, plan.pieces)
    net = fit_canvas(task, NetConfig(features=plan.features))
    mcts = MCTSConfig(simulations=plan.simulations)
    workload = SingleTask.of(task, net.canvas_side())
    rows = []
    sample: dict = {}
    for nodes in plan.nodes:
        with local_cluster(nodes, cores):
            for actors in plan.actors:
                learner = Learner(
                    workload, net, LearnerConfig(batch_size=plan.batch_size), jax.random.PRNGKey(0)
                )
                row, sample = _measure(workload, net, mcts, plan, actors, learner)
                rows.append({"nodes": nodes, **row})
                log.info(
                    "%d node(s), %d actor(s): %.3f episodes/s, %.1f learner steps/s",
                    nodes,
                    actors,
                    row["episodes_per_sec"],
                    row["learner_steps_per_sec"],
                )
    return {
        "plan": asdict(plan),
        "cores": cores,
        "canvas": net.canvas,
        "rows": rows,
        "learner_alone_steps_per_sec": learner_alone(workload, net, plan, sample),
    }


def format_scaling(result: dict) -> str:
    plan, rows = result["plan"], result["rows"]
    lines = [
        f"scaling: {plan['shape']} K={plan['pieces']}, {plan['simulations']} simulations, "
        f"{plan['episodes_per_batch']} episodes a batch, {result['cores']} cores, "
        f"{plan['seconds']:g} s windows",
        "| nodes | actors | on nodes | CPUs per actor | episodes/s | x vs fewest actors | of linear "
        "| learner steps/s | KiB/episode | broadcast ms | empty call ms |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        one = next(x for x in rows if x["nodes"] == r["nodes"])  # the fewest actors on these nodes
        speedup = r["episodes_per_sec"] / max(one["episodes_per_sec"], 1e-12)
        linear = speedup * one["actors"] / r["actors"]
        lines.append(
            f"| {r['nodes']} | {r['actors']} | {r['actor_nodes']} | {r['cpus_per_actor']:g} | "
            f"{r['episodes_per_sec']:.3f} | "
            f"x{speedup:.2f} | {linear:.0%} | {r['learner_steps_per_sec']:.1f} | "
            f"{r['bytes_per_episode'] / 1024:.1f} | {r['broadcast_ms']:.1f} | {r['call_ms']:.1f} |"
        )
    for r in rows:
        same = next((x for x in rows if x["nodes"] == 1 and x["actors"] == r["actors"]), None)
        if r["nodes"] > 1 and same:
            lines.append(
                f"{r['actors']} actor(s), {r['nodes']} nodes against 1: episodes/s "
                f"x{r['episodes_per_sec'] / max(same['episodes_per_sec'], 1e-12):.2f}, learner steps/s "
                f"x{r['learner_steps_per_sec'] / max(same['learner_steps_per_sec'], 1e-12):.2f}"
            )
    alone = result["learner_alone_steps_per_sec"]
    lines.append(
        f"learner alone (batch {plan['batch_size']}): "
        + ", ".join(f"{p} {v:.1f} steps/s" for p, v in alone.items())
        + (f" (gpu x{alone['gpu'] / alone['cpu']:.1f} the cpu)" if "gpu" in alone else "")
    )
    return "\n".join(lines) + "\n"
