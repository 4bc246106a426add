"""`rllock train`: self-play actors on Ray, a replay buffer actor, and the JAX learner in this process.

Data flow: each actor plays a lockstep batch of episodes with the weights version it was handed, pushes
the episodes into the replay buffer actor and returns its statistics; this process then hands it the
newest weights (one `ray.put` per version, fetched by an actor only when the version changed). Exactly
one batch is in flight per actor, and the learner stops publishing while the oldest batch in flight is
`max_policy_lag` versions behind (`pacing.Pacing`). The learner starts once the buffer holds a batch,
takes at most `replay_ratio` sampled transitions per transition produced, validates on fixed seeds
(`validation`) every `validate_minutes` when the budget has room for it, and keeps:
  LOGDIR/checkpoints/<step>/  the latest checkpoints (orbax: learner state + metadata with the config,
                              the task and the counters); the first right after the first learner step
  LOGDIR/best/<step>/         the checkpoint with the best validation
  LOGDIR/best_assembly/       the best validation assembly so far (verified), with its picture
  LOGDIR/replay.npz           the replay buffer, snapshotted atomically with every checkpoint
  TensorBoard event files
`--minutes` is a hard budget: the run returns within it plus 30 s, its last checkpoint included.
`rllock train --resume LOGDIR` continues from the newest readable checkpoint (an unreadable one is
skipped with a warning) with its config, optimizer state, PRNG key, counters, best score and replay
buffer. Ctrl-C stops cleanly: a final checkpoint and snapshot, then Ray is shut down.
"""

from __future__ import annotations

import dataclasses
import logging
import signal
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np
import ray
from ray.exceptions import RayTaskError

from actors.selfplay import TaskSpec
from learner.learner import Learner
from learner.replay import ReplayBuffer
from orchestration import validation
from orchestration.pacing import Pacing, Schedule, final_reserve, validation_estimate
from orchestration.pool import (
    ActorPool,
    NodeWatch,
    describe_node,
    driver_node,
    driver_node_cpus,
    largest_node_cpus,
    on_driver_node,
    plan_layout,
    start_ray,
)
from orchestration.recorder import Counters, Recorder, best_rank
from rllock.config import TrainConfig
from rllock.core.env import Task, compact_dtypes, make_task
from rllock.core.feasibility import check_feasible
from rllock.core.tasks import TaskSet, parse_tasks
from rllock.errors import RLLockError
from rllock.files import checkpoint as ckpt
from rllock.process import peak_rss_mb
from rllock.search.inference import load_network
from rllock.search.methods import space
from rllock.search.network import fit_canvas

log = logging.getLogger(__name__)


def _restore_latest(logdir: Path, learner: Learner) -> ckpt.Metadata:
    """Load the newest readable checkpoint into `learner`; returns its metadata."""
    for step in ckpt.saved_steps(logdir / "checkpoints")[::-1]:
        step_dir = logdir / "checkpoints" / str(step)
        try:
            meta = ckpt.read_metadata(step_dir)
            learner.load_state(ckpt.restore_like(step_dir, learner.state()))
        except RLLockError as exc:
            log.warning("%s; falling back to the checkpoint before it", exc)
            continue
        return meta
    raise RLLockError(f"cannot resume {logdir}: every checkpoint is unreadable")


def _setup(
    config: TrainConfig, *, resume: bool = False
) -> tuple[TrainConfig, Task | None, TaskSet | None, dict, ckpt.Checkpoint | None]:
    """(the config with a concrete network, the task or the task set, what the run is for, and the
    checkpoint to start from when --init names one, its parameters not read yet: no JAX array is made
    here). A resumed run's saved config already holds the --init checkpoint's network settings, so that
    checkpoint is not read again."""
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
        return dataclasses.replace(config, net=net), None, tasks, tasks.identity(), init
    assert config.shape is not None and config.pieces is not None
    task = make_task(config.shape, config.pieces, config.removal, resolution=config.resolution)
    check_feasible(task)
    canvas_of = (
        None if init is None or config.net.canvas is not None else f"the --init checkpoint {config.init}"
    )
    net = fit_canvas(task, net, canvas_of)
    return dataclasses.replace(config, net=net), task, None, ckpt.task_identity(task, net.canvas_side()), init


def _resume(logdir: Path, learner: Learner, identity: dict) -> tuple[Counters, dict | None, list[dict]]:
    """Restore the newest readable checkpoint of `logdir` into `learner`; (its counters, its last
    validation, the sessions that trained the run)."""
    meta = _restore_latest(logdir, learner)
    ckpt.check_same_task(meta.task, identity, logdir)
    counters = Counters(**meta.counters)
    # The best checkpoint may be newer than the latest readable one: its own score is the bar.
    counters.best_rate, counters.best_return = max(
        (counters.best_rate, counters.best_return), best_rank(logdir)
    )
    log.info("resuming %s at learner step %d (%d episodes so far)", logdir, learner.step, counters.episodes)
    return counters, meta.validation, list(meta.sessions)


def train(config: TrainConfig, *, resume: bool = False) -> dict:
    began = time.monotonic()
    config.validate()
    config, task, tasks, identity, init = _setup(config, resume=resume)
    logdir = Path(config.logdir)
    if not resume and ckpt.saved_steps(logdir / "checkpoints"):
        raise RLLockError(
            f"{logdir} already holds a training run; resume it with --resume {logdir} "
            f"or choose another --logdir"
        )
    # Ray starts its processes with fork() (and Python code in the child): after JAX has started its
    # threads, with the learner's first array, that can deadlock. So Ray starts first.
    started_ray = start_ray(config.address)
    try:
        return _train(config, task, tasks, identity, init, resume, began)
    finally:
        if started_ray:
            ray.shutdown()


def _train(
    config: TrainConfig,
    task: Task | None,
    tasks: TaskSet | None,
    identity: dict,
    init: ckpt.Checkpoint | None,
    resume: bool,
    began: float,
) -> dict:
    logdir = Path(config.logdir)
    learner = Learner(task, config.net, config.learner, jax.random.PRNGKey(config.seed), config.method)
    counters, last_score = Counters(), None
    sessions: list[dict] = []
    if resume:
        counters, last_score, sessions = _resume(logdir, learner, identity)
    elif init is not None:
        learner.start_from(load_network(init)[2])
        log.info("starting from the network of %s", config.init)
    recorder = Recorder(logdir, config, task or identity, learner.step, resume, sessions)
    run = _Run(config, task, tasks, learner, recorder, counters, last_score, began)
    # SIGTERM (`kill`, `ray job stop`, a scheduler) stops a run as Ctrl-C does: a final checkpoint first.
    previous = {s: signal.signal(s, run.request_stop) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        return run.loop(resume)
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        recorder.close()
        if run.interrupted:
            log.warning(
                "stopped by %s at learner step %d; checkpoint saved. Resume with: rllock train --resume %s",
                _signal_name(run.stop_signal),
                learner.step,
                logdir,
            )


def _signal_name(signum: int | None) -> str:
    return "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum or signal.SIGTERM).name


def _buffer_shape(
    config: TrainConfig, task: Task | None, tasks: TaskSet | None
) -> tuple[tuple[int, ...], tuple[type[np.signedinteger], type[np.signedinteger]]]:
    """The replay buffer's transition shape (states, candidates, piece size) and its two dtypes."""
    if tasks is None:
        assert task is not None
        return (task.size, *space(config.method).action_shape(task, config.mcts)), compact_dtypes(task)
    # canvas states (rllock.search.canvas)
    return (tasks.store_canvas**3, config.mcts.candidates, tasks.max_piece_size()), (np.int8, np.int16)


class _Run:
    """The actor-learner loop's state: what a checkpoint must capture, in one place."""

    def __init__(
        self,
        config: TrainConfig,
        task: Task | None,
        tasks: TaskSet | None,
        learner: Learner,
        recorder: Recorder,
        counters: Counters,
        last_score: dict | None,
        began: float,
    ):
        self.config, self.task, self.tasks = config, task, tasks
        self.learner, self.recorder = learner, recorder
        self.counters, self.last_score = counters, last_score
        self.pacing = Pacing.of(config)
        self.began = began
        self.schedule = Schedule.start(began, config)
        self.validation_plan = validation.Plan.of(config, task, tasks)
        self.interrupted = False
        self.stop_signal: int | None = None  # the signal that stopped the run (SIGINT or SIGTERM)
        self.lag = 0
        # The fastest self-play batch so far (the first includes compiling), to estimate a validation.
        self.batch_seconds: float | None = None
        self.validation_seconds: float | None = None
        self.buffer_successes = 0
        self.memory = {"driver": 0.0, "buffer": 0.0, "actor": 0.0}  # peak resident MiB per process kind

    def request_stop(self, signum, frame) -> None:
        del frame
        if self.interrupted:  # a second signal: stop at once
            raise KeyboardInterrupt
        self.interrupted, self.stop_signal = True, signum
        log.warning("%s: saving a checkpoint and stopping (again to abort)", _signal_name(signum))

    def loop(self, resume: bool) -> dict:
        self.buffer = self._start_buffer(resume)
        pool = self._start_pool()
        try:
            self._selfplay(pool)
            if self.interrupted:
                # SIGKILL may follow a SIGTERM within seconds (`ray job stop` waits 3 s unless the head
                # was started with RAY_JOB_STOP_WAIT_TIME_S): the checkpoint comes before anything else.
                self._final_checkpoint()
        finally:
            pool.shutdown()  # batches under way are dropped: the budget is a hard limit
        if not self.interrupted:
            self._validate_if_it_fits(time.monotonic(), final=True)
            self._final_checkpoint()
        return self._result()

    def _final_checkpoint(self) -> None:
        self._charts()  # the curves end at the final step
        self._checkpoint()

    def _start_buffer(self, resume: bool) -> Any:
        """The replay buffer actor, holding the run's snapshot when resumed. Its handle is Any: Ray types an
        ActorHandle's methods as Never, and mypy checks nothing after a call of one."""
        shape, dtypes = _buffer_shape(self.config, self.task, self.tasks)
        # It snapshots into the run's folder, so it runs where the folder is: the driver's node.
        buffer: Any = (
            ray.remote(num_cpus=0)(ReplayBuffer)
            .options(scheduling_strategy=on_driver_node())
            .remote(
                self.config.buffer_capacity,
                *shape,
                *dtypes,
                store_canvas=None if self.tasks is None else self.tasks.store_canvas,
            )
        )
        snapshot = self.recorder.logdir / "replay.npz"
        if resume and snapshot.exists():
            try:
                restored = ray.get(buffer.restore.remote(str(snapshot)))
            except RayTaskError as exc:  # the buffer actor's own error, without Ray's traceback around it
                cause = exc.cause if isinstance(exc.cause, RLLockError) else None
                raise RLLockError(str(cause or exc).splitlines()[0]) from None
            log.info("replay buffer restored: %d transitions", restored)
        log.info("learner and replay buffer on %s, with the run's folder", describe_node(driver_node()))
        return buffer

    def _start_pool(self) -> ActorPool:
        """The self-play actors, laid out over the cluster's free CPUs and GPUs."""
        config = self.config
        resources = ray.cluster_resources()
        self.layout = layout = plan_layout(
            config.selfplay,
            cpus=resources.get("CPU", 1),
            gpus=resources.get("GPU", 0),
            # the learner's core, where it is a Ray CPU: a head started with --num-cpus=0 lends none
            reserved_cpus=min(1.0, driver_node_cpus()),
            node_cpus=largest_node_cpus(),
        )
        spec, described = self._played()
        pool = ActorPool(
            spec,
            config.net,
            config.mcts,
            config.method,
            layout,
            config.seed * 1000 + 1 + self.counters.episodes,
            self.buffer,
        )
        log.info(
            "training %s: %d self-play actor(s) (%s, %d episodes each, %d thread(s)) for %g min; logs in %s",
            described,
            layout.actors,
            layout.mode,
            layout.episodes,
            layout.threads,
            config.minutes,
            self.recorder.logdir,
        )
        return pool

    def _played(self) -> tuple[TaskSpec | TaskSet, str]:
        """What the self-play actors play, and its name for the log."""
        if self.tasks is not None:
            return self.tasks, f"tasks {self.tasks.spec}"
        if self.task is None:
            raise ValueError("a run needs a task or a task set")
        return TaskSpec.of(self.task), f"{self.task.shape_name} K={self.task.pieces}"

    def _selfplay(self, pool: ActorPool) -> None:
        """Self-play and learn until a stop signal, the last learner step, or the end of the budget less
        what the final validation needs."""
        c, learner = self.counters, self.learner
        weights = [ray.put(jax.device_get(learner.params))]
        pool.submit_all(weights, c.version)
        start, base_seconds = time.monotonic(), c.seconds
        nodes = NodeWatch.start()
        while (
            not self.interrupted and self._selfplay_time_left() and not self.pacing.reached_max(learner.step)
        ):
            weights = self._turn(pool, weights)
            c.seconds = base_seconds + time.monotonic() - start
            nodes.check(time.monotonic(), pool)
            self._periodic(time.monotonic())
        c.seconds = base_seconds + time.monotonic() - start

    def _selfplay_time_left(self) -> bool:
        """Whether the budget has time left once the final validation's share is kept for it."""
        return not self.schedule.over(
            time.monotonic() + final_reserve(self._validation_estimate(), self.config)
        )

    def _turn(self, pool: ActorPool, weights: list[ray.ObjectRef]) -> list[ray.ObjectRef]:
        """Collect the finished batches (waiting up to 1 s for one when the learner may not step), hand
        their actors the current weights, then take a learner step if pacing allows; returns the weights
        to hand out next."""
        c, learner = self.counters, self.learner
        oldest = pool.oldest_version()
        can_learn = self.pacing.can_learn(
            step=learner.step,
            transitions=c.transitions,
            version=c.version,
            oldest_version=c.version if oldest is None else oldest,
        )
        timeout = 0.0 if can_learn else min(1.0, max(0.0, self.schedule.deadline - time.monotonic()))
        for actor, stats in pool.collect(timeout, weights):
            self._count(stats)
            pool.submit(actor, weights, c.version)
        if can_learn and self._learn():
            return [ray.put(jax.device_get(learner.params))]
        return weights

    def _result(self) -> dict:
        c = self.counters
        return {
            "steps": self.learner.step,
            "episodes": c.episodes,
            "selfplay_success_rate": c.successes / max(c.episodes, 1),
            "validation": self.last_score,
            "best_success_rate": c.best_rate,
            "seconds": time.monotonic() - self.began,
            "episodes_per_sec": c.episodes / max(c.seconds, 1e-9),
            "simulations_per_sec": c.simulations / max(c.seconds, 1e-9),
            "actors": self.layout.actors,
            "logdir": str(self.recorder.logdir),
            "interrupted": self.interrupted,
            "stop_signal": self.stop_signal,
            "peak_rss_mb": dict(self.memory),
        }

    def _count(self, stats) -> None:
        c = self.counters
        c.add(stats)
        self.lag = c.version - stats.version
        self.batch_seconds = min(stats.seconds, self.batch_seconds or stats.seconds)
        self.memory["actor"] = max(self.memory["actor"], stats.peak_rss_mb)
        buffer_stats: dict[str, float] = ray.get(self.buffer.stats.remote())
        c.transitions = int(buffer_stats["added"])
        self.buffer_successes = int(buffer_stats["successes"])
        self.memory["buffer"] = buffer_stats["peak_rss_mb"]

    def _learn(self) -> bool:
        """One learner step; True when it published a new weights version."""
        learner, c = self.learner, self.counters
        sample: dict[str, np.ndarray] = ray.get(
            self.buffer.sample.remote(
                self.config.learner.batch_size, learner.next_seed(), self.config.success_fraction
            )
        )
        losses = learner.update(sample)
        if learner.step % 10 == 0 or learner.step == 1:
            self.recorder.scalars(
                {
                    "losses/policy": losses["policy"],
                    "losses/value": losses["value"],
                    "losses/total": losses["policy"] + losses["value"],
                },
                learner.step,
            )
        if learner.step % self.config.publish_every == 0:
            c.version += 1
            return True
        return False

    def _periodic(self, now: float) -> None:
        step, schedule = self.learner.step, self.schedule
        if schedule.report_due(now):
            self._charts()
            c = self.counters
            log.info(
                "step %d | episodes %d | self-play success %.1f%% | validation %s | lag %d | "
                "peak MiB driver %.0f buffer %.0f actor %.0f | %.0f s",
                step,
                c.episodes,
                100 * c.successes / max(c.episodes, 1),
                "-" if self.last_score is None else f"{100 * self.last_score['success_rate']:.1f}%",
                self.lag,
                self.memory["driver"],
                self.memory["buffer"],
                self.memory["actor"],
                c.seconds,
            )
        if schedule.checkpoint_due(now, step):
            self._checkpoint()
            schedule.checkpointed(time.monotonic())
        if schedule.validation_due(now) and not self.interrupted:
            self._validate_if_it_fits(now, final=False)
            schedule.validated(time.monotonic())

    def _charts(self) -> None:
        c, step = self.counters, self.learner.step
        self.memory["driver"] = peak_rss_mb()
        seconds = max(c.seconds, 1e-9)
        self.recorder.scalars(
            {
                "charts/episodes_per_sec": c.episodes / seconds,
                "charts/simulations_per_sec": c.simulations / seconds,
                "charts/learner_steps_per_sec": step / seconds,
                "charts/policy_lag": self.lag,
                "charts/selfplay_success_rate": c.successes / max(c.episodes, 1),
                "buffer/size": min(c.transitions, self.config.buffer_capacity),
                "buffer/success_transitions": self.buffer_successes,
                **{f"memory/{kind}_peak_mb": mb for kind, mb in self.memory.items()},
            },
            step,
        )

    def _checkpoint(self) -> None:
        ray.get(self.buffer.snapshot.remote(str(self.recorder.logdir / "replay.npz")))
        self.recorder.checkpoint(self.learner.step, self.learner.state(), self.last_score, self.counters)

    def _validation_estimate(self) -> float | None:
        return validation_estimate(
            self.batch_seconds,
            self.layout.episodes,
            self.layout.groups,
            self.validation_plan.total_episodes,
            self.validation_seconds,
        )

    def _validate_if_it_fits(self, now: float, *, final: bool) -> None:
        estimate = self._validation_estimate()
        if not self.schedule.fits(now, estimate, final=final):
            need = (
                "no self-play batch has finished yet to time it"
                if estimate is None
                else f"about {estimate:.0f} s of the budget would be needed"
            )
            log.info(
                "%svalidation skipped: %s, %.0f s are left",
                "final " if final else "",
                need,
                max(0.0, self.schedule.deadline - now),
            )
            return
        self._validate()

    def _validate(self) -> None:
        step, plan = self.learner.step, self.validation_plan
        result = validation.summarize(plan, validation.play(plan, self.learner.params))
        score = self.last_score = result.score
        self.validation_seconds = score["seconds"]
        self.recorder.scalars(validation.scalars(score), step)
        log.info(
            "validation at step %d: %d/%d valid (%.1f%%) in %.0f s",
            step,
            score["valid"],
            score["episodes"],
            100 * score["success_rate"],
            score["seconds"],
        )
        validation.keep_best(result, self.learner, self.recorder, self.counters)
