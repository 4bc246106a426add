"""`rllock train`: self-play actors on Ray, a replay buffer actor, and the JAX learner in this process.

Data flow: each actor plays a lockstep batch of episodes with the weights version it was handed, pushes
the episodes into the replay buffer actor (waiting for it: bounded in-flight data), and returns its
statistics; this process then hands it the newest weights (one `ray.put` per version, fetched by an actor
only when the version changed). Exactly one batch is in flight per actor, and the learner stops
publishing while the oldest batch in flight is `max_policy_lag` versions behind. The learner samples
mini-batches once the buffer holds `min_buffer` transitions, at most `replay_ratio` sampled transitions
per transition produced, validates on fixed seeds every `validate_minutes`, and keeps:
  LOGDIR/checkpoints/<step>/  the latest checkpoints (orbax: learner state + metadata with the counters)
  LOGDIR/best/<step>/         the checkpoint with the best validation success rate
  LOGDIR/best_assembly/       the best validation assembly so far (verified), with its picture
  LOGDIR/replay.npz           the replay buffer, snapshotted atomically with every checkpoint
  LOGDIR/config.json, TensorBoard event files
`rllock train --resume LOGDIR` continues from the newest readable checkpoint (an unreadable one is
skipped with a warning) with its optimizer state, PRNG key, counters, best score and replay buffer.
Ctrl-C stops cleanly: a final checkpoint and snapshot, then Ray is shut down.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import jax
import numpy as np
import ray
from PIL import Image
from ray.exceptions import RayActorError
from tensorboardX import SummaryWriter

from actors.selfplay import ACTOR_ENV, SelfPlayActor, SelfPlayConfig, TaskSpec, evaluate
from learner.learner import Learner
from learner.replay import ReplayBuffer
from rllock import checkpoint as ckpt
from rllock.config import TrainConfig
from rllock.assembly import write_assembly
from rllock.env import Task, compact_dtypes, final_labels, make_task, peak_rss_mb
from rllock.errors import RLLockError
from rllock.mcts import Searcher
from rllock.network import PolicyValueNet, check_fits
from rllock.render import draw_png

log = logging.getLogger(__name__)


@dataclass
class Counters:
    """Run totals that survive a resume (saved in every checkpoint's metadata)."""

    episodes: int = 0
    successes: int = 0
    simulations: int = 0
    transitions: int = 0
    seconds: float = 0.0
    best_rate: float = -1.0
    best_return: float = -1.0  # mean return of the best validation, which breaks ties in success rate
    version: int = 0

    def add(self, stats) -> None:
        """Count one finished self-play batch (`actors.selfplay.PlayStats`)."""
        self.episodes += stats.episodes
        self.successes += stats.successes
        self.simulations += stats.simulations


def checkpoint_meta(config: TrainConfig, task: Task, step: int, validation: dict | None,
                    counters: Counters | None = None) -> dict:
    return {
        "format": ckpt.FORMAT, "version": 1, "step": step, "task": ckpt.task_identity(task, config.canvas),
        "train": asdict(config), "net": asdict(config.net()), "mcts": asdict(config.mcts()),
        "learner": asdict(config.learner()), "validation": validation,
        "counters": asdict(counters or Counters()),
    }


@dataclass
class Validator:
    """Validation episodes with fixed seeds, so that scores are comparable across the run."""

    searcher: Searcher
    task: Task
    config: TrainConfig

    def __call__(self, params) -> tuple[dict, np.ndarray | None]:
        """The score, and the label grid of one valid assembly found (None if none)."""
        episodes, seconds = evaluate(self.searcher, params, self.task, jax.random.PRNGKey(self.config.seed + 7),
                                     batch=self.config.validation_episodes, seed=self.config.seed + 7,
                                     canvas=self.config.canvas)
        wins = [e for e in episodes if e.success]
        mean_return = float(np.mean([e.final.placed for e in episodes])) / self.task.pieces
        score = {"success_rate": len(wins) / len(episodes), "valid": len(wins), "episodes": len(episodes),
                 "mean_return": mean_return,
                 "seconds": seconds, "time_per_valid_s": seconds / len(wins) if wins else None}
        grid = self.task.topology.to_grid(final_labels(self.task, wins[0].final)) if wins else None
        return score, grid


def _start_ray(config: TrainConfig) -> bool:
    """Connect to Ray; True when this process started the instance (and so must shut it down)."""
    if ray.is_initialized():
        return False
    if config.address:
        ray.init(address=config.address, logging_level=logging.WARNING)
    else:
        ray.init(num_cpus=os.cpu_count(), include_dashboard=False, logging_level=logging.WARNING)
    return True


def _actor_count(config: TrainConfig) -> int:
    if config.actors > 0:
        return config.actors
    return max(1, int(ray.cluster_resources().get("CPU", 2)) - 1)


def load_resume(logdir: Path, minutes: float | None) -> TrainConfig:
    """The config of the run in `logdir` (with `minutes` more to train, if given)."""
    try:
        doc = json.loads((logdir / "config.json").read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise RLLockError(f"cannot resume {logdir}: no readable config.json ({exc})") from None
    config = TrainConfig.from_json(doc)
    values = asdict(config) | {"logdir": str(logdir)} | ({"minutes": minutes} if minutes else {})
    return TrainConfig(**values)


def _restore_latest(logdir: Path, learner: Learner) -> dict:
    """Load the newest readable checkpoint into `learner`; returns its metadata."""
    steps = ckpt.saved_steps(logdir / "checkpoints")[::-1]
    if not steps:
        raise RLLockError(f"cannot resume {logdir}: it holds no checkpoint (start it again without --resume)")
    for step in steps:
        step_dir = logdir / "checkpoints" / str(step)
        try:
            meta = ckpt.read_meta(step_dir)
            learner.load_state(ckpt.restore_like(step_dir, learner.state()))
        except RLLockError as exc:
            log.warning("%s; falling back to the checkpoint before it", exc)
            continue
        return meta
    raise RLLockError(f"cannot resume {logdir}: every checkpoint is unreadable")


def validation_rank(score: dict | None) -> tuple[float, float]:
    """How validations compare: success rate first, then the mean return (how far the episodes got),
    so that a hard task where no validation succeeds yet still keeps its most promising checkpoint."""
    score = score or {}
    return float(score.get("success_rate", -1.0)), float(score.get("mean_return", -1.0))


def _best_rank(logdir: Path) -> tuple[float, float]:
    """The validation rank of the run's best checkpoint ((-1, -1) when there is none yet)."""
    steps = ckpt.saved_steps(logdir / "best")
    if not steps:
        return -1.0, -1.0
    return validation_rank(ckpt.read_meta(logdir / "best" / str(steps[-1])).get("validation"))


def train(config: TrainConfig, *, resume: bool = False) -> dict:
    config.validate()
    task = make_task(config.shape, config.pieces, config.removal, resolution=config.resolution)
    check_fits(task, config.net())
    logdir = Path(config.logdir)
    learner = Learner(task, config.net(), config.learner(), jax.random.PRNGKey(config.seed))
    counters = Counters()
    last_score = None
    if resume:
        meta = _restore_latest(logdir, learner)
        ckpt.check_same_task(meta["task"], ckpt.task_identity(task, config.canvas), logdir)
        counters = Counters(**meta.get("counters", {}))
        # The best checkpoint may be newer than the latest readable one: its own score is the bar.
        counters.best_rate, counters.best_return = max((counters.best_rate, counters.best_return),
                                                       _best_rank(logdir))
        last_score = meta.get("validation")
        log.info("resuming %s at learner step %d (%d episodes so far)", logdir, learner.step, counters.episodes)
    elif ckpt.saved_steps(logdir / "checkpoints"):
        raise RLLockError(f"{logdir} already holds a training run; resume it with --resume {logdir} "
                          f"or choose another --logdir")
    logdir.mkdir(parents=True, exist_ok=True)
    (logdir / "config.json").write_text(json.dumps(asdict(config), indent=1))
    # purge_step drops events logged after the checkpoint we resume from, so the curves do not fork.
    writer = SummaryWriter(str(logdir), purge_step=learner.step if resume else None)
    writer.add_text("config", "```\n" + json.dumps(asdict(config), indent=1) + "\n```", learner.step)
    latest_mngr = ckpt.manager(logdir / "checkpoints", keep=3)
    best_mngr = ckpt.manager(logdir / "best", keep=1)
    validator = Validator(Searcher(PolicyValueNet(config.net()), config.mcts(), config.canvas, task.piece_size,
                                   config.validation_episodes), task, config)
    started_ray = _start_ray(config)
    loop = _Loop(config, task, learner, validator, writer, latest_mngr, best_mngr, logdir, counters, last_score,
                 resume)
    previous = signal.signal(signal.SIGINT, loop.request_stop)
    try:
        return loop.run()
    finally:
        signal.signal(signal.SIGINT, previous)
        writer.close()
        latest_mngr.close()
        best_mngr.close()
        if started_ray:
            ray.shutdown()
        if loop.interrupted:
            log.warning("stopped by Ctrl-C at learner step %d; checkpoint saved. Resume with: "
                        "rllock train --resume %s", learner.step, logdir)


class _Loop:
    """The actor-learner loop's state: what a checkpoint must capture, in one place."""

    def __init__(self, config, task, learner, validator, writer, latest_mngr, best_mngr, logdir, counters,
                 last_score, resume):
        self.config, self.task, self.learner, self.validator = config, task, learner, validator
        self.writer, self.latest_mngr, self.best_mngr, self.logdir = writer, latest_mngr, best_mngr, logdir
        self.counters, self.last_score = counters, last_score
        self.interrupted = False
        self.resume = resume
        self.lag = 0
        self.buffer_successes = 0  # transitions of successful episodes in the buffer
        self.memory = {"driver": 0.0, "buffer": 0.0, "actor": 0.0}  # peak resident MiB per process kind

    def request_stop(self, signum, frame) -> None:
        del signum, frame
        if self.interrupted:  # a second Ctrl-C: stop at once
            raise KeyboardInterrupt
        self.interrupted = True
        log.warning("Ctrl-C: saving a checkpoint and stopping (press again to abort)")

    def run(self) -> dict:
        config, task, learner, c = self.config, self.task, self.learner, self.counters
        self.buffer = ray.remote(num_cpus=0)(ReplayBuffer).remote(
            config.buffer_capacity, task.size, config.candidates, task.piece_size, *compact_dtypes(task))
        snapshot = self.logdir / "replay.npz"
        if self.resume and snapshot.exists():
            restored = ray.get(self.buffer.restore.remote(str(snapshot)))
            log.info("replay buffer restored: %d transitions", restored)
        n_actors = _actor_count(config)
        play_config = SelfPlayConfig(config.episodes_per_batch, config.mcts(), config.net())
        # A dead actor process is restarted by Ray and its call retried (max_restarts, max_task_retries).
        actors = [SelfPlayActor.options(runtime_env={"env_vars": ACTOR_ENV}, max_restarts=-1,
                                        max_task_retries=-1).remote(
            TaskSpec.of(task), play_config, config.seed * 1000 + i + 1 + c.episodes, self.buffer)
            for i in range(n_actors)]
        log.info("training %s K=%d with %d self-play actor(s) for %g min; logs in %s", task.shape_name,
                 task.pieces, n_actors, config.minutes, self.logdir)
        # Each actor's process id, so that a restart (a new process behind the same handle) is noticed.
        pids = {id(a): pid for a, pid in zip(actors, ray.get([a.pid.remote() for a in actors]))}
        weights = [ray.put(jax.device_get(learner.params))]
        inflight = {actor.run.remote(weights, c.version): (actor, c.version) for actor in actors}
        start = time.monotonic()
        base_seconds = c.seconds
        deadline = start + 60 * config.minutes
        next_validate = start + 60 * config.validate_minutes
        next_checkpoint = start + 60 * config.checkpoint_minutes
        next_report = start + 30
        while time.monotonic() < deadline and not self.interrupted:
            oldest = min(v for _, v in inflight.values())
            can_learn = (c.transitions >= config.min_buffer
                         and (learner.step + 1) * config.batch_size <= config.replay_ratio * c.transitions
                         and c.version - oldest < config.max_policy_lag)
            ready, _ = ray.wait(list(inflight), num_returns=1, timeout=0 if can_learn else 1.0)
            for ref in ready:
                actor, _ = inflight.pop(ref)
                try:
                    stats = ray.get(ref)
                except RayActorError as exc:  # restarts exhausted or the node is gone: go on without it
                    log.error("a self-play actor failed for good: %s", str(exc).splitlines()[0])
                    continue
                if pids[id(actor)] != stats.pid:
                    log.warning("self-play actor restarted (pid %d -> %d)", pids[id(actor)], stats.pid)
                pids[id(actor)] = stats.pid
                c.add(stats)
                self.lag = c.version - stats.version
                buffer_stats = ray.get(self.buffer.stats.remote())
                c.transitions = int(buffer_stats["added"])
                self.buffer_successes = int(buffer_stats["successes"])
                self.memory["actor"] = max(self.memory["actor"], stats.peak_rss_mb)
                self.memory["buffer"] = buffer_stats["peak_rss_mb"]
                inflight[actor.run.remote(weights, c.version)] = (actor, c.version)
            if not inflight:
                raise RLLockError("every self-play actor has failed; see the log above")
            if can_learn:
                sample = ray.get(self.buffer.sample.remote(config.batch_size, learner.next_seed(),
                                                           config.success_fraction))
                losses = learner.update(sample)
                if learner.step % config.publish_every == 0:
                    c.version += 1
                    weights = [ray.put(jax.device_get(learner.params))]
                if learner.step % 10 == 0:
                    self.writer.add_scalar("losses/policy", losses["policy"], learner.step)
                    self.writer.add_scalar("losses/value", losses["value"], learner.step)
                    self.writer.add_scalar("losses/total", losses["policy"] + losses["value"], learner.step)
            now = time.monotonic()
            c.seconds = base_seconds + now - start
            if ready or now >= next_report:
                self._charts()
            if now >= next_report:
                log.info("step %d | episodes %d | self-play success %.1f%% | validation %s | lag %d | "
                         "peak MiB driver %.0f buffer %.0f actor %.0f | %.0f s",
                         learner.step, c.episodes, 100 * c.successes / max(c.episodes, 1),
                         "-" if self.last_score is None else f"{100 * self.last_score['success_rate']:.1f}%",
                         self.lag, self.memory["driver"], self.memory["buffer"], self.memory["actor"], c.seconds)
                next_report = now + 30
            if now >= next_checkpoint:
                self._checkpoint()
                next_checkpoint = now + 60 * config.checkpoint_minutes
            if now >= next_validate and not self.interrupted:
                self._validate()
                next_validate = time.monotonic() + 60 * config.validate_minutes
        c.seconds = base_seconds + time.monotonic() - start
        self._charts()  # the curves end at the final step
        if self.interrupted:
            self._checkpoint()
        else:
            for ref in inflight:  # batches under way finish before the final evaluation
                try:
                    c.add(ray.get(ref))
                except RayActorError:
                    log.error("a self-play actor failed while finishing its last batch")
            self._validate()
            self._checkpoint()
        elapsed = time.monotonic() - start
        return {"steps": learner.step, "episodes": c.episodes, "selfplay_success_rate": c.successes / max(c.episodes, 1),
                "validation": self.last_score, "best_success_rate": c.best_rate, "seconds": elapsed,
                "episodes_per_sec": c.episodes / max(c.seconds, 1e-9),
                "simulations_per_sec": c.simulations / max(c.seconds, 1e-9),
                "actors": len(actors), "logdir": str(self.logdir), "interrupted": self.interrupted,
                "peak_rss_mb": dict(self.memory)}

    def _charts(self) -> None:
        c, step, w = self.counters, self.learner.step, self.writer
        w.add_scalar("charts/episodes_per_sec", c.episodes / max(c.seconds, 1e-9), step)
        w.add_scalar("charts/simulations_per_sec", c.simulations / max(c.seconds, 1e-9), step)
        w.add_scalar("charts/learner_steps_per_sec", step / max(c.seconds, 1e-9), step)
        w.add_scalar("charts/policy_lag", self.lag, step)
        w.add_scalar("charts/selfplay_success_rate", c.successes / max(c.episodes, 1), step)
        w.add_scalar("buffer/size", min(c.transitions, self.config.buffer_capacity), step)
        w.add_scalar("buffer/success_transitions", self.buffer_successes, step)
        self.memory["driver"] = peak_rss_mb()
        for kind, mb in self.memory.items():
            w.add_scalar(f"memory/{kind}_peak_mb", mb, step)

    def _checkpoint(self) -> None:
        step = self.learner.step
        snapshot = self.logdir / "replay.npz"
        ray.get(self.buffer.snapshot.remote(str(snapshot)))
        ckpt.save(self.latest_mngr, step, self.learner.state(),
                  checkpoint_meta(self.config, self.task, step, self.last_score, self.counters))

    def _validate(self) -> None:
        c, step = self.counters, self.learner.step
        score, grid = self.validator(self.learner.params)
        self.last_score = score
        self.writer.add_scalar("validation/success_rate", score["success_rate"], step)
        if score["time_per_valid_s"] is not None:
            self.writer.add_scalar("validation/time_per_valid_s", score["time_per_valid_s"], step)
        log.info("validation at step %d: %d/%d valid (%.1f%%)", step, score["valid"], score["episodes"],
                 100 * score["success_rate"])
        self.writer.add_scalar("validation/mean_return", score["mean_return"], step)
        if validation_rank(score) > (c.best_rate, c.best_return) or self.best_mngr.latest_step() is None:
            c.best_rate, c.best_return = max(validation_rank(score), (c.best_rate, c.best_return))
            ckpt.save(self.best_mngr, step, self.learner.state(),
                      checkpoint_meta(self.config, self.task, step, score, self.counters))
            if grid is not None:
                self._best_assembly(grid, step)

    def _best_assembly(self, grid: np.ndarray, step: int) -> None:
        folder = self.logdir / "best_assembly"
        png = folder / "assembly.png"
        png.unlink(missing_ok=True)  # never leave the previous best's picture beside the new assembly
        write_assembly(folder, grid, removal=self.task.removal, shape=self.task.shape_name,
                       method={"name": "rl-lock validation", "step": step}, seed=self.config.seed,
                       timings={})
        if not png.exists():  # the CLI registers the picture writer; direct callers may not
            draw_png(grid, png, self.task.removal)
        self.writer.add_image("best/assembly", np.asarray(Image.open(png).convert("RGB")), step,
                              dataformats="HWC")
