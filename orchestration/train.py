"""`rllock train`: self-play actors on Ray, a replay buffer actor, and the JAX learner in this process.

Data flow: each actor plays a lockstep batch of episodes with the weights version it was handed, pushes
the episodes into the replay buffer actor and returns its statistics; this process then hands it the
newest weights (one `ray.put` per version, fetched by an actor only when the version changed). Exactly
one batch is in flight per actor, and the learner stops publishing while the oldest batch in flight is
`max_policy_lag` versions behind (`pacing.Pacing`). The learner starts once the buffer holds a batch,
takes at most `replay_ratio` sampled transitions per transition produced, validates on fixed seeds every
`validate_minutes` when the budget has room for it, and keeps:
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
import re
import signal
import time
from pathlib import Path

import jax
import numpy as np
import ray
from ray.exceptions import RayTaskError

from actors.selfplay import TaskSpec, evaluate
from learner.learner import Learner
from learner.replay import ReplayBuffer
from orchestration.pacing import Pacing, Schedule, final_reserve, validation_estimate
from orchestration.pool import ActorPool, largest_node_cpus, plan_layout, start_ray
from orchestration.recorder import Counters, Recorder, best_rank, validation_rank
from rllock.config import TrainConfig
from rllock.core.env import Task, compact_dtypes, final_labels, make_task
from rllock.core.tasks import TaskSet, parse_tasks
from rllock.errors import RLLockError
from rllock.files import checkpoint as ckpt
from rllock.process import peak_rss_mb
from rllock.search.inference import load_network
from rllock.search.methods import players, space, with_method_defaults
from rllock.search.network import fit_canvas

log = logging.getLogger(__name__)


def _restore_latest(logdir: Path, learner: Learner) -> dict:
    """Load the newest readable checkpoint into `learner`; returns its metadata."""
    for step in ckpt.saved_steps(logdir / "checkpoints")[::-1]:
        step_dir = logdir / "checkpoints" / str(step)
        try:
            meta = ckpt.read_meta(step_dir)
            learner.load_state(ckpt.restore_like(step_dir, learner.state()))
        except RLLockError as exc:
            log.warning("%s; falling back to the checkpoint before it", exc)
            continue
        return meta
    raise RLLockError(f"cannot resume {logdir}: every checkpoint is unreadable")


def _setup(
    config: TrainConfig, *, resume: bool = False
) -> tuple[TrainConfig, Task | None, TaskSet | None, dict, dict | None]:
    """(the config with a concrete network, the task or the task set, what the run is for, and the
    parameters to start from when --init names a checkpoint). A resumed run's saved config already
    holds the --init checkpoint's network settings, so that checkpoint is not read again."""
    init = None
    net = config.net
    if config.init is not None and not resume:
        _, _, net, _, init = load_network(config.init)
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
    canvas_of = (
        None if init is None or config.net.canvas is not None else f"the --init checkpoint {config.init}"
    )
    net = fit_canvas(task, net, canvas_of)
    return dataclasses.replace(config, net=net), task, None, ckpt.task_identity(task, net.canvas), init


def train(config: TrainConfig, *, resume: bool = False) -> dict:
    began = time.monotonic()
    config.validate()
    config, task, tasks, identity, init = _setup(with_method_defaults(config), resume=resume)
    logdir = Path(config.logdir)
    learner = Learner(task, config.net, config.learner, jax.random.PRNGKey(config.seed), config.method)
    counters, last_score, sessions = Counters(), None, []
    if resume:
        meta = _restore_latest(logdir, learner)
        ckpt.check_same_task(meta["task"], identity, logdir)
        counters = Counters(**meta.get("counters", {}))
        # The best checkpoint may be newer than the latest readable one: its own score is the bar.
        counters.best_rate, counters.best_return = max(
            (counters.best_rate, counters.best_return), best_rank(logdir)
        )
        last_score = meta.get("validation")
        sessions = meta.get("sessions", [])
        log.info(
            "resuming %s at learner step %d (%d episodes so far)", logdir, learner.step, counters.episodes
        )
    elif ckpt.saved_steps(logdir / "checkpoints"):
        raise RLLockError(
            f"{logdir} already holds a training run; resume it with --resume {logdir} "
            f"or choose another --logdir"
        )
    elif init is not None:
        learner.start_from(init)
        log.info("starting from the network of %s", config.init)
    recorder = Recorder(logdir, config, task or identity, learner.step, resume, sessions)
    started_ray = start_ray(config.address)
    run = _Run(config, task, tasks, learner, recorder, counters, last_score, began)
    previous = signal.signal(signal.SIGINT, run.request_stop)
    try:
        return run.loop(resume)
    finally:
        signal.signal(signal.SIGINT, previous)
        recorder.close()
        if started_ray:
            ray.shutdown()
        if run.interrupted:
            log.warning(
                "stopped by Ctrl-C at learner step %d; checkpoint saved. Resume with: "
                "rllock train --resume %s",
                learner.step,
                logdir,
            )


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
        # Validation runs in this process beside the learner, one lockstep group per task: the run's
        # task, or one fixed task per group of a multi-task run.
        self.space = space(config.method)
        self.validation_tasks = [task] if tasks is None else tasks.validation_tasks(config.seed + 7)
        self.searchers = [
            players(config.method, config.net, config.mcts, t, config.validation_episodes, 1)
            for t in self.validation_tasks
        ]
        self.interrupted = False
        self.lag = 0
        # The fastest self-play batch so far (the first includes compiling), to estimate a validation.
        self.batch_seconds: float | None = None
        self.validation_seconds: float | None = None
        self.buffer_successes = 0
        self.memory = {"driver": 0.0, "buffer": 0.0, "actor": 0.0}  # peak resident MiB per process kind

    def request_stop(self, signum, frame) -> None:
        del signum, frame
        if self.interrupted:  # a second Ctrl-C: stop at once
            raise KeyboardInterrupt
        self.interrupted = True
        log.warning("Ctrl-C: saving a checkpoint and stopping (press again to abort)")

    def loop(self, resume: bool) -> dict:
        config, c, learner = self.config, self.counters, self.learner
        if self.tasks is None:
            assert self.task is not None
            shape = (self.task.size, *self.space.action_shape(self.task, config.mcts))
            dtypes = compact_dtypes(self.task)
        else:  # canvas states (rllock.search.canvas)
            shape = (self.tasks.canvas**3, config.mcts.candidates, self.tasks.max_piece_size())
            dtypes = (np.int8, np.int16)
        self.buffer = ray.remote(num_cpus=0)(ReplayBuffer).remote(config.buffer_capacity, *shape, *dtypes)
        snapshot = self.recorder.logdir / "replay.npz"
        if resume and snapshot.exists():
            try:
                restored = ray.get(self.buffer.restore.remote(str(snapshot)))
            except RayTaskError as exc:  # the buffer actor's own error, without Ray's traceback around it
                cause = exc.cause if isinstance(exc.cause, RLLockError) else None
                raise RLLockError(str(cause or exc).splitlines()[0]) from None
            log.info("replay buffer restored: %d transitions", restored)
        resources = ray.cluster_resources()
        layout = plan_layout(
            config.selfplay,
            cpus=resources.get("CPU", 1),
            gpus=resources.get("GPU", 0),
            reserved_cpus=1,
            node_cpus=largest_node_cpus(),
        )
        pool = ActorPool(
            TaskSpec.of(self.task) if self.tasks is None else self.tasks,
            config.net,
            config.mcts,
            config.method,
            layout,
            config.seed * 1000 + 1 + c.episodes,
            self.buffer,
        )
        log.info(
            "training %s: %d self-play actor(s) (%s, %d episodes each, %d thread(s)) for %g min; logs in %s",
            f"{self.task.shape_name} K={self.task.pieces}" if self.task else f"tasks {self.tasks.spec}",
            layout.actors,
            layout.mode,
            layout.episodes,
            layout.threads,
            config.minutes,
            self.recorder.logdir,
        )
        weights = [ray.put(jax.device_get(learner.params))]
        pool.submit_all(weights, c.version)
        start, base_seconds = time.monotonic(), c.seconds
        self.layout = layout
        while (
            not self.interrupted
            and not self.schedule.over(time.monotonic() + final_reserve(self._validation_estimate(), config))
            and not self.pacing.reached_max(learner.step)
        ):
            oldest = pool.oldest_version()
            can_learn = self.pacing.can_learn(
                step=learner.step,
                transitions=c.transitions,
                version=c.version,
                oldest_version=c.version if oldest is None else oldest,
            )
            timeout = 0.0 if can_learn else min(1.0, max(0.0, self.schedule.deadline - time.monotonic()))
            for actor, stats in pool.collect(timeout):
                self._count(stats)
                pool.submit(actor, weights, c.version)
            if not pool.alive():
                raise RLLockError("every self-play actor has failed; see the log above")
            if can_learn and self._learn():
                weights = [ray.put(jax.device_get(learner.params))]
            c.seconds = base_seconds + time.monotonic() - start
            self._periodic(time.monotonic())
        pool.shutdown()  # batches under way are dropped: the budget is a hard limit
        c.seconds = base_seconds + time.monotonic() - start
        self._charts()  # the curves end at the final step
        if not self.interrupted:
            self._validate_if_it_fits(time.monotonic(), final=True)
        self._checkpoint()
        return {
            "steps": learner.step,
            "episodes": c.episodes,
            "selfplay_success_rate": c.successes / max(c.episodes, 1),
            "validation": self.last_score,
            "best_success_rate": c.best_rate,
            "seconds": time.monotonic() - self.began,
            "episodes_per_sec": c.episodes / max(c.seconds, 1e-9),
            "simulations_per_sec": c.simulations / max(c.seconds, 1e-9),
            "actors": layout.actors,
            "logdir": str(self.recorder.logdir),
            "interrupted": self.interrupted,
            "peak_rss_mb": dict(self.memory),
        }

    def _count(self, stats) -> None:
        c = self.counters
        c.add(stats)
        self.lag = c.version - stats.version
        self.batch_seconds = min(stats.seconds, self.batch_seconds or stats.seconds)
        self.memory["actor"] = max(self.memory["actor"], stats.peak_rss_mb)
        buffer_stats = ray.get(self.buffer.stats.remote())
        c.transitions = int(buffer_stats["added"])
        self.buffer_successes = int(buffer_stats["successes"])
        self.memory["buffer"] = buffer_stats["peak_rss_mb"]

    def _learn(self) -> bool:
        """One learner step; True when it published a new weights version."""
        learner, c = self.learner, self.counters
        sample = ray.get(
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
            self.config.validation_episodes * len(self.validation_tasks),
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
        c, step = self.counters, self.learner.step
        seed = self.config.seed + 7
        scores, wins = [], []
        for task, searchers in zip(self.validation_tasks, self.searchers):
            episodes, seconds = evaluate(
                searchers, self.learner.params, task, jax.random.PRNGKey(seed), seed=seed
            )
            won = [e for e in episodes if e.success]
            wins += [(task, e) for e in won]
            scores.append(
                {
                    "task": f"{task.shape_name} K={task.pieces}",
                    "success_rate": len(won) / len(episodes),
                    "valid": len(won),
                    "episodes": len(episodes),
                    "mean_return": float(np.mean([e.final.placed for e in episodes])) / task.pieces,
                    "seconds": seconds,
                }
            )
        seconds = sum(s["seconds"] for s in scores)
        score = {
            "success_rate": float(np.mean([s["success_rate"] for s in scores])),
            "valid": len(wins),
            "episodes": sum(s["episodes"] for s in scores),
            "mean_return": float(np.mean([s["mean_return"] for s in scores])),
            "seconds": seconds,
            "time_per_valid_s": seconds / len(wins) if wins else None,
        }
        if self.tasks is not None:
            score["groups"] = {group.spec: s for group, s in zip(self.tasks.groups, scores)}
            for group, s in score["groups"].items():
                tag = re.sub(r"[^\w.\-]", "_", group)  # TensorBoard's tag characters: cube4_6-9
                self.recorder.scalars(
                    {
                        f"validation/{tag}/success_rate": s["success_rate"],
                        f"validation/{tag}/mean_return": s["mean_return"],
                    },
                    step,
                )
        self.validation_seconds = seconds
        self.last_score = score
        self.recorder.scalars(
            {
                "validation/success_rate": score["success_rate"],
                "validation/mean_return": score["mean_return"],
            },
            step,
        )
        if wins:
            self.recorder.scalars({"validation/time_per_valid_s": score["time_per_valid_s"]}, step)
        log.info(
            "validation at step %d: %d/%d valid (%.1f%%) in %.0f s",
            step,
            score["valid"],
            score["episodes"],
            100 * score["success_rate"],
            seconds,
        )
        if validation_rank(score) > (c.best_rate, c.best_return) or self.recorder.best.latest_step() is None:
            c.best_rate, c.best_return = max(validation_rank(score), (c.best_rate, c.best_return))
            assembly = None
            if wins:
                task, episode = wins[0]
                assembly = (task, task.topology.to_grid(final_labels(task, episode.final)))
            self.recorder.best_checkpoint(step, self.learner.state(), score, c, assembly)
