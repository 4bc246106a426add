"""The trainer's wiring (acme's builder is the model): one place turns a run's config into what the
actor-learner loop (`orchestration.train`) runs on: the workload, the learner (fresh, resumed or started
from another run's network), the recorder, the replay buffer actor and the self-play actor pool."""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import ray
from ray.exceptions import RayTaskError

from learner.learner import Learner
from learner.replay import ReplayBuffer
from orchestration.pool import (
    ActorPool,
    Layout,
    describe_node,
    driver_node,
    driver_node_cpus,
    largest_node_cpus,
    on_driver_node,
    plan_layout,
)
from orchestration.recorder import Counters, Recorder, best_rank
from orchestration.validation import Score
from rllock.config import TrainConfig
from rllock.core.env import make_task
from rllock.core.feasibility import check_feasible
from rllock.core.identity import check_same_task
from rllock.core.tasks import parse_tasks
from rllock.errors import RLLockError
from rllock.files import checkpoint as ckpt
from rllock.files.orbax_io import restore_like
from rllock.search.inference import load_network
from rllock.search.network import fit_canvas
from rllock.search.workload import ManyTasks, SingleTask, Workload

log = logging.getLogger(__name__)


def workload_of(
    config: TrainConfig, *, resume: bool = False
) -> tuple[TrainConfig, Workload, ckpt.Checkpoint | None]:
    """(the config with a concrete network, what the run plays, and the checkpoint to start from when
    --init names one, its parameters not read yet: no JAX array is made here). A resumed run's saved
    config already holds the --init checkpoint's network settings, so that checkpoint is not read again."""
    init = None
    net = config.net
    if config.init is not None and not resume:
        init = ckpt.open_checkpoint(config.init)
        net = init.metadata.config.net
        if config.net.canvas is not None:
            # The U-Net's weights do not depend on the canvas side, so a generalist trained on a large
            # canvas can be fine-tuned on the smallest one that fits the task, where search is cheaper.
            net = dataclasses.replace(net, canvas=config.net.canvas)
    if config.tasks is not None:
        tasks = parse_tasks(config.tasks, canvas=net.canvas, removal=config.removal, step=net.levels_step())
        net = dataclasses.replace(net, canvas=tasks.canvas, task_planes=True)
        return dataclasses.replace(config, net=net), ManyTasks(tasks), init
    assert config.shape is not None and config.pieces is not None  # TrainConfig.validate
    task = make_task(config.shape, config.pieces, config.removal, resolution=config.resolution)
    check_feasible(task)
    canvas_of = (
        None if init is None or config.net.canvas is not None else f"the --init checkpoint {config.init}"
    )
    net = fit_canvas(task, net, canvas_of)
    return dataclasses.replace(config, net=net), SingleTask.of(task, net.canvas_side()), init


@dataclass
class Start:
    """Where a run starts: its counters, its last validation and the sessions that trained it before."""

    counters: Counters
    last_score: Score | None
    sessions: list[dict]


def start_learner(
    config: TrainConfig, workload: Workload, init: ckpt.Checkpoint | None, resume: bool
) -> tuple[Learner, Start]:
    """The learner, fresh, started from `init`'s network, or resumed from the run's newest readable
    checkpoint (which must be for the same task)."""
    logdir = Path(config.logdir)
    learner = Learner(workload, config.net, config.learner, jax.random.PRNGKey(config.seed), config.method)
    if not resume:
        if init is not None:
            learner.start_from(load_network(init)[2])
            log.info("starting from the network of %s", config.init)
        return learner, Start(Counters(), None, [])

    def restore(step_dir: Path) -> ckpt.Metadata:
        meta = ckpt.read_metadata(step_dir)
        learner.load_state(restore_like(step_dir, learner.state()))
        return meta

    meta = ckpt.newest_readable(logdir, restore)
    check_same_task(meta.task, workload.identity(), logdir)
    counters = Counters(**meta.counters)
    # The best checkpoint may be newer than the latest readable one: its own score is the bar.
    counters.best_rate, counters.best_return = max(
        (counters.best_rate, counters.best_return), best_rank(logdir)
    )
    log.info("resuming %s at learner step %d (%d episodes so far)", logdir, learner.step, counters.episodes)
    last = None if meta.validation is None else Score.from_json(meta.validation)
    return learner, Start(counters, last, list(meta.sessions))


def start_buffer(config: TrainConfig, workload: Workload, recorder: Recorder, resume: bool) -> Any:
    """The replay buffer actor, holding the run's snapshot when resumed. Its handle is Any: Ray types an
    ActorHandle's methods as Never, and mypy checks nothing after a call of one."""
    layout = workload.buffer_layout(config.method, config.mcts)
    # It snapshots into the run's folder, so it runs where the folder is: the driver's node.
    buffer: Any = (
        ray.remote(num_cpus=0)(ReplayBuffer)
        .options(scheduling_strategy=on_driver_node())
        .remote(config.buffer_capacity, *layout.shape, *layout.dtypes, store_canvas=layout.store_canvas)
    )
    snapshot = recorder.logdir / "replay.npz"
    if resume and snapshot.exists():
        try:
            restored = ray.get(buffer.restore.remote(str(snapshot)))
        except RayTaskError as exc:  # the buffer actor's own error, without Ray's traceback around it
            cause = exc.cause if isinstance(exc.cause, RLLockError) else None
            raise RLLockError(str(cause or exc).splitlines()[0]) from None
        log.info("replay buffer restored: %d transitions", restored)
    log.info("learner and replay buffer on %s, with the run's folder", describe_node(driver_node()))
    return buffer


def start_pool(config: TrainConfig, workload: Workload, buffer: Any, episodes_so_far: int) -> ActorPool:
    """The self-play actors, laid out over the cluster's free CPUs and GPUs."""
    resources = ray.cluster_resources()
    layout: Layout = plan_layout(
        config.selfplay,
        cpus=resources.get("CPU", 1),
        gpus=resources.get("GPU", 0),
        # the learner's core, where it is a Ray CPU: a head started with --num-cpus=0 lends none
        reserved_cpus=min(1.0, driver_node_cpus()),
        node_cpus=largest_node_cpus(),
    )
    seed = config.seed * 1000 + 1 + episodes_so_far
    pool = ActorPool(workload, config.net, config.mcts, config.method, layout, seed, buffer)
    log.info(
        "training %s: %d self-play actor(s) (%s, %d episodes each, %d thread(s)) for %g min; logs in %s",
        workload.describe(),
        layout.actors,
        layout.mode,
        layout.episodes,
        layout.threads,
        config.minutes,
        config.logdir,
    )
    return pool
