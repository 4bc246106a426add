"""The trainers' builder (acme's builder is the model): a trainer's config becomes the parts the one
actor-learner loop (`rllock.orchestration.loop`) runs, and `run` runs them. The trainers differ only in these
parts and their config:

  rllock train        self-play actors (`pool.ActorPool`) -> transitions
                      (`rllock.learner.replay.ReplayBuffer`) -> the policy-value learner
                      (`rllock.learner.learner.Learner`), fresh, resumed or started from another run's
                      network
  rllock train-guide  search actors (`pool.SearchPool`) -> labelled states
                      (`rllock.learner.guide_learner.GuideBuffer`) -> the guide's learner (`GuideLearner`);
                      with --replay-from, no actors: the states of snapshots already made, in this process

Both keep their replay buffer in a Ray actor on the driver's node (it snapshots into the run's folder)
and resume from the run's newest readable checkpoint with its counters and replay snapshot.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import ray
from ray.exceptions import RayTaskError

from rllock.actors.guide_actor import SearchTotals
from rllock.actors.selfplay import PlayTotals
from rllock.config import GuideTrainConfig, TrainConfig
from rllock.core.env import Task, make_task
from rllock.core.feasibility import check_feasible
from rllock.core.identity import check_same_task
from rllock.core.tasks import parse_tasks
from rllock.errors import RLLockError
from rllock.files import checkpoint as ckpt
from rllock.files.orbax_io import restore_like
from rllock.learner.guide_learner import GuideBuffer, GuideLearner
from rllock.learner.learner import Learner
from rllock.learner.replay import ReplayBuffer
from rllock.orchestration.guide_offline import load_pool
from rllock.orchestration.loop import Actors, Learning, Loop, M, Replay, System
from rllock.orchestration.pacing import Pacing, Schedule
from rllock.orchestration.pool import (
    ActorPool,
    NoActors,
    SearchPool,
    describe_node,
    driver_node,
    driver_node_cpus,
    largest_node_cpus,
    on_driver_node,
    plan_layout,
    start_ray,
)
from rllock.orchestration.recorder import Counters, Recorder, best_rank, totals_of
from rllock.orchestration.stopping import StopRequest, stop_on_signals
from rllock.orchestration.validation import Score
from rllock.search.curriculum import named_tasks
from rllock.search.guide import channels
from rllock.search.guide_checkpoint import read_guide_metadata
from rllock.search.inference import load_network
from rllock.search.network import fit_canvas
from rllock.search.workload import ManyTasks, SingleTask, Workload

log = logging.getLogger(__name__)


class Builder(ABC):
    """A trainer's parts, made from its config in the order `run` asks for them; what a part needs to
    know of another it keeps (the learner, the buffer actor's handle)."""

    kind: str  # what the log directory holds once trained: "training run", "guide run"
    config: Any
    logdir: Path
    address: str | None  # the Ray cluster to join (None: a local Ray instance)
    uses_ray: bool = True
    task: Task | dict | None = None  # the recorder's (`Recorder`): None for a guide run
    extra: dict | None = None  # the recorder's: what else every checkpoint records
    publish_every: int | None = None  # learner steps between weights versions

    @abstractmethod
    def make_learner(self, resume: bool) -> tuple[Learning, Counters, list[dict]]:
        """The learner, fresh or resumed from the run's newest readable checkpoint; the run's counters;
        the sessions that trained it before."""

    @abstractmethod
    def make_buffer(self, resume: bool) -> Replay:
        """The replay buffer, holding the run's snapshot when resumed."""

    @abstractmethod
    def make_actors(self) -> Actors: ...

    @abstractmethod
    def pacing(self) -> Pacing: ...

    @abstractmethod
    def schedule(self, began: float) -> Schedule: ...


def run(builder: Builder, monitor: Callable[[System], M], *, resume: bool, began: float) -> Loop[M]:
    """Build the trainer and run the loop, with `monitor(system)` watching it, until the budget (from
    `began`), the step limit or a stop signal ends it; the loop as it ended."""
    if not resume and ckpt.saved_steps(builder.logdir / "checkpoints"):
        raise RLLockError(
            f"{builder.logdir} already holds a {builder.kind}; resume it with --resume {builder.logdir} "
            f"or choose another --logdir"
        )
    # Ray starts its processes with fork() (and Python code in the child): after JAX has started its
    # threads, with the learner's first array, that can deadlock. So Ray starts first.
    started_ray = builder.uses_ray and start_ray(builder.address)
    try:
        learner, counters, sessions = builder.make_learner(resume)
        recorder = Recorder(
            builder.logdir, builder.config, builder.task, learner.step, resume, sessions, builder.extra
        )
        stop = StopRequest()
        try:
            with stop_on_signals(stop):
                buffer = builder.make_buffer(resume)
                actors = builder.make_actors()
                system = System(
                    learner,
                    buffer,
                    actors,
                    counters,
                    recorder,
                    builder.pacing(),
                    builder.schedule(began),
                    builder.publish_every,
                    resume,
                )
                loop = Loop(system, monitor(system), stop)
                loop.run()
        finally:
            recorder.close()
        return loop
    finally:
        if started_ray:
            ray.shutdown()


@dataclass
class RemoteReplay:
    """A replay buffer actor (`start_buffer`); `options` go with every sample (self-play's success
    fraction)."""

    handle: Any  # Any: Ray types an ActorHandle's methods as Never, and mypy checks nothing after one
    path: Path  # the run's snapshot
    options: tuple = ()

    def sample(self, batch: int, seed: int) -> dict:
        return ray.get(self.handle.sample.remote(batch, seed, *self.options))

    def snapshot(self) -> None:
        ray.get(self.handle.snapshot.remote(str(self.path)))


@dataclass
class PooledReplay:
    """The states of replay snapshots already made, in this process (`guide_offline.load_pool`)."""

    buffer: GuideBuffer

    def sample(self, batch: int, seed: int) -> dict:
        return self.buffer.sample(batch, seed)

    def snapshot(self) -> None:
        pass  # the snapshots it holds are on disk already, and every checkpoint names them


def start_buffer(kind: type, args: tuple, kwargs: dict, snapshot: Path, resume: bool, items: str) -> Any:
    """A replay buffer actor `kind(*args, **kwargs)` on the driver's node, whose disk holds the run's
    folder it snapshots into, holding the run's `snapshot` of `items` when resumed."""
    handle: Any = (
        ray.remote(num_cpus=0)(kind).options(scheduling_strategy=on_driver_node()).remote(*args, **kwargs)
    )
    if resume and snapshot.exists():
        try:
            restored = ray.get(handle.restore.remote(str(snapshot)))
        except RayTaskError as exc:  # the buffer actor's own error, without Ray's traceback around it
            cause = exc.cause if isinstance(exc.cause, RLLockError) else None
            raise RLLockError(str(cause or exc).splitlines()[0]) from None
        log.info("replay buffer restored: %d %s", restored, items)
    return handle


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


class SelfPlayBuilder(Builder):
    """`rllock train`. Its config is checked and its workload made before Ray starts, so that a bad
    setting is one line."""

    kind = "training run"

    def __init__(self, config: TrainConfig, *, resume: bool):
        config.validate()
        self.config, self.workload, self.init = workload_of(config, resume=resume)
        self.logdir, self.address = Path(self.config.logdir), self.config.address
        self.task, self.publish_every = self.workload.identity(), self.config.publish_every
        self.totals = PlayTotals()
        self.last_score: Score | None = None  # the last validation's, when resumed

    def make_learner(self, resume: bool) -> tuple[Learner, Counters, list[dict]]:
        """Started from `init`'s network, or resumed from a checkpoint that must be for the same task."""
        c = self.config
        learner = Learner(self.workload, c.net, c.learner, jax.random.PRNGKey(c.seed), c.method)
        self.learner = learner
        if not resume:
            if self.init is not None:
                learner.start_from(load_network(self.init)[2])
                log.info("starting from the network of %s", c.init)
            return learner, Counters(self.totals, best=(-1.0, -1.0)), []

        def restore(step_dir: Path) -> ckpt.Metadata:
            meta = ckpt.read_metadata(step_dir)
            learner.load_state(restore_like(step_dir, learner.state()))
            return meta

        meta = ckpt.newest_readable(self.logdir, restore)
        check_same_task(meta.task, self.workload.identity(), self.logdir)
        self.totals = totals_of(PlayTotals, meta.counters)
        counters = Counters.of(meta.counters, self.totals, validates=True)
        # The best checkpoint may be newer than the latest readable one: its own score is the bar.
        counters.best = max(counters.best or (-1.0, -1.0), best_rank(self.logdir))
        log.info(
            "resuming %s at learner step %d (%d episodes so far)",
            self.logdir,
            learner.step,
            self.totals.episodes,
        )
        self.last_score = None if meta.validation is None else Score.from_json(meta.validation)
        return learner, counters, list(meta.sessions)

    def make_buffer(self, resume: bool) -> RemoteReplay:
        c, layout = self.config, self.workload.buffer_layout(self.config.method, self.config.mcts)
        path = self.logdir / "replay.npz"
        args = (c.buffer_capacity, *layout.shape, *layout.dtypes)
        kwargs = {"store_canvas": layout.store_canvas}
        self.handle = start_buffer(ReplayBuffer, args, kwargs, path, resume, "transitions")
        log.info("learner and replay buffer on %s, with the run's folder", describe_node(driver_node()))
        return RemoteReplay(self.handle, path, (c.success_fraction,))

    def make_actors(self) -> ActorPool:
        """The self-play actors, laid out over the cluster's free CPUs and GPUs."""
        c, resources = self.config, ray.cluster_resources()
        layout = plan_layout(
            c.selfplay,
            cpus=resources.get("CPU", 1),
            gpus=resources.get("GPU", 0),
            # the learner's core, where it is a Ray CPU: a head started with --num-cpus=0 lends none
            reserved_cpus=min(1.0, driver_node_cpus()),
            node_cpus=largest_node_cpus(),
        )
        seed = c.seed * 1000 + 1 + self.totals.episodes
        self.pool = ActorPool(self.workload, c.net, c.mcts, c.method, layout, seed, self.handle)
        log.info(
            "training %s: %d self-play actor(s) (%s, %d episodes each, %d thread(s)) for %g min; logs in %s",
            self.workload.describe(),
            layout.actors,
            layout.mode,
            layout.episodes,
            layout.threads,
            c.minutes,
            c.logdir,
        )
        return self.pool

    def pacing(self) -> Pacing:
        return Pacing.of(self.config)

    def schedule(self, began: float) -> Schedule:
        return Schedule.start(began, self.config)


JUDGED_NODES = 200  # nodes held out, and as many trained on, judged at each checkpoint of a guide run


class GuideBuilder(Builder):
    """`rllock train-guide` with search actors. Its budget keeps no reserve and its first checkpoint comes
    `checkpoint_minutes` in; its cells are read before Ray starts, so that a bad one is one line."""

    kind = "guide run"

    def __init__(self, config: GuideTrainConfig):
        config.validate()
        self.config, self.logdir, self.address = config, Path(config.logdir), config.address
        self.publish_every = config.publish_every
        self.cells = {task.shape_name: task for task in self._named()}
        self.totals = SearchTotals()

    def _named(self) -> list[Task]:
        return named_tasks(self.config.cells) if self.config.cells else []

    def make_learner(self, resume: bool) -> tuple[GuideLearner, Counters, list[dict]]:
        c = self.config
        learner = GuideLearner(
            c.guide, c.guide_learning_rate, jax.random.PRNGKey(c.seed), c.rank_weight, c.weight_average
        )
        self.learner, self.totals = learner, self._fresh_totals()
        counted: dict = {}
        sessions: list[dict] = []
        if resume:

            def restore(step_dir: Path) -> dict:
                doc = read_guide_metadata(step_dir)
                learner.load_state(restore_like(step_dir, learner.state()))
                return doc

            doc = ckpt.newest_readable(self.logdir, restore)
            self._check_resumable(doc)
            counted, sessions = doc.get("counters", {}), list(doc.get("sessions", []))
            self.totals = totals_of(SearchTotals, counted)
            self._log_resume()
        if self.cells and self.config.edge and not self.totals.edge:
            self.totals.edge = {label: task.pieces for label, task in self.cells.items()}
        return learner, Counters.of(counted, self.totals), sessions

    def _check_resumable(self, doc: dict) -> None:
        pass

    def _fresh_totals(self) -> SearchTotals:
        return SearchTotals()

    def _log_resume(self) -> None:
        log.info(
            "resuming %s at learner step %d (%d searches so far)",
            self.logdir,
            self.learner.step,
            self.totals.searches,
        )

    def make_buffer(self, resume: bool) -> Replay:
        c, path = self.config, self.logdir / "replay.npz"
        args = (c.buffer_capacity, c.guide.window, channels(c.guide))
        self.handle = start_buffer(GuideBuffer, args, {}, path, resume, "states")
        return RemoteReplay(self.handle, path)

    def make_actors(self) -> Actors:
        return SearchPool(self.config, self.handle, self.totals)

    def nodes(self, held_out: bool) -> dict:
        """Nodes of the buffer, held out of training or trained on, for the guide's judgement."""
        return ray.get(self.handle.nodes.remote(held_out, JUDGED_NODES, self.learner.step))

    def pacing(self) -> Pacing:
        c = self.config
        return Pacing(c.batch_size, c.batch_size, c.replay_ratio, None, c.max_learner_steps)

    def schedule(self, began: float) -> Schedule:
        c = self.config
        return Schedule.of(
            began,
            minutes=c.minutes,
            checkpoint_minutes=c.checkpoint_minutes,
            reserve_s=0.0,
            checkpoint_first_step=False,
        )


class OfflineGuideBuilder(GuideBuilder):
    """`rllock train-guide --replay-from`: the guide's learner alone, on every state of replay snapshots
    already made (`guide_offline.load_pool`), in this process: no Ray, no actors. Every checkpoint records
    the snapshots it learned from, and a resume must find the same ones (by their hashes)."""

    uses_ray = False

    def __init__(self, config: GuideTrainConfig):
        super().__init__(config)
        self.pooled, self.replay = load_pool(config)
        self.extra, self.publish_every = {"replay": self.replay}, None
        log.info("%d states from %d snapshot(s): %s", self.pooled.size, len(self.replay), config.replay_from)

    def _named(self) -> list[Task]:
        return []  # no curriculum: the states are there already

    def _check_resumable(self, doc: dict) -> None:
        if [r["sha256"] for r in doc.get("replay", [])] != [r["sha256"] for r in self.replay]:
            raise RLLockError(
                f"cannot resume {self.logdir}: its replay snapshots are not the ones it was trained on"
            )

    def _fresh_totals(self) -> SearchTotals:
        return SearchTotals(states=self.pooled.size)

    def _log_resume(self) -> None:
        log.info("resuming %s at learner step %d", self.logdir, self.learner.step)

    def make_buffer(self, resume: bool) -> Replay:
        return PooledReplay(self.pooled)

    def make_actors(self) -> Actors:
        return NoActors()

    def nodes(self, held_out: bool) -> dict:
        return self.pooled.nodes(held_out, self.pooled.size, self.learner.step)  # every node: it is here

    def pacing(self) -> Pacing:
        c = self.config
        return Pacing(1, c.batch_size, math.inf, None, c.max_learner_steps)
