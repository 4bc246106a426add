"""`rllock train`: self-play actors on Ray, a replay buffer actor, and the JAX learner in this process.

Data flow: each actor plays a lockstep batch of episodes with the weights version it was handed, pushes
the episodes into the replay buffer actor (waiting for it: bounded in-flight data), and returns its
statistics; this process then hands it the newest weights (one `ray.put` per version, fetched by an actor
only when the version changed). Exactly one batch is in flight per actor. The learner samples
mini-batches once the buffer holds `min_buffer` transitions, at most `replay_ratio` sampled transitions
per transition produced, validates on fixed seeds every `validate_minutes`, keeps the best checkpoint in
`LOGDIR/best/`, the latest ones in `LOGDIR/checkpoints/`, and TensorBoard event files in LOGDIR.
"""

from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import jax
import ray
from tensorboardX import SummaryWriter

from actors.selfplay import ACTOR_ENV, SelfPlayActor, SelfPlayConfig, TaskSpec, evaluate
from learner.learner import Learner, LearnerConfig
from learner.replay import ReplayBuffer
from rllock import checkpoint as ckpt
from rllock.env import Task, make_task
from rllock.errors import RLLockError
from rllock.mcts import MCTSConfig, Searcher
from rllock.network import NetConfig, PolicyValueNet, check_fits

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrainConfig:
    shape: str
    """Built-in name or shape file."""
    pieces: int
    """K."""
    removal: str = "straight"
    resolution: int | None = None
    """For mesh shapes: voxels along the longest side."""
    actors: int = 0
    """Self-play actors; 0 = one per CPU core left after the learner's."""
    minutes: float = 10.0
    """Wall-clock training time."""
    logdir: str = "runs/latest"
    seed: int = 0
    address: str | None = None
    """Join this Ray cluster instead of starting a local Ray instance."""
    canvas: int = 8
    features: tuple[int, ...] = (16, 32, 64)
    simulations: int = 256
    max_considered: int = 16
    raw_samples: int = 1024
    candidates: int = 32
    episodes_per_batch: int = 8
    learning_rate: float = 5e-5
    batch_size: int = 64
    buffer_capacity: int = 50_000
    """Transitions kept; the oldest are overwritten."""
    min_buffer: int = 256
    """Transitions in the buffer before the learner starts."""
    replay_ratio: float = 4.0
    """At most this many sampled transitions per transition produced by self-play."""
    publish_every: int = 25
    """Learner steps between weight versions."""
    validate_minutes: float = 5.0
    validation_episodes: int = 64
    checkpoint_minutes: float = 2.0

    def net(self) -> NetConfig:
        return NetConfig(canvas=self.canvas, features=tuple(self.features))

    def mcts(self) -> MCTSConfig:
        return MCTSConfig(simulations=self.simulations, max_considered=self.max_considered,
                          raw_samples=self.raw_samples, candidates=self.candidates)

    def learner(self) -> LearnerConfig:
        return LearnerConfig(learning_rate=self.learning_rate, batch_size=self.batch_size)


def checkpoint_meta(config: TrainConfig, task: Task, step: int, validation: dict | None) -> dict:
    return {
        "format": ckpt.FORMAT, "version": 1, "step": step, "task": ckpt.task_identity(task, config.canvas),
        "train": asdict(config), "net": asdict(config.net()), "mcts": asdict(config.mcts()),
        "learner": asdict(config.learner()), "validation": validation,
    }


@dataclass
class Validator:
    """Validation episodes with fixed seeds, so that scores are comparable across the run."""

    searcher: Searcher
    task: Task
    config: TrainConfig

    def __call__(self, params) -> dict:
        episodes, seconds = evaluate(self.searcher, params, self.task, jax.random.PRNGKey(self.config.seed + 7),
                                     batch=self.config.validation_episodes, seed=self.config.seed + 7,
                                     canvas=self.config.canvas)
        wins = [e for e in episodes if e.success]
        return {"success_rate": len(wins) / len(episodes), "valid": len(wins), "episodes": len(episodes),
                "seconds": seconds, "time_per_valid_s": seconds / len(wins) if wins else None}


def _start_ray(config: TrainConfig) -> bool:
    """Connect to Ray; True when this process started the instance (and so must shut it down)."""
    if ray.is_initialized():
        return False
    if config.address:
        ray.init(address=config.address, logging_level=logging.WARNING)
        return True
    ray.init(num_cpus=os.cpu_count(), include_dashboard=False, logging_level=logging.WARNING)
    return True


def _actor_count(config: TrainConfig) -> int:
    if config.actors > 0:
        return config.actors
    return max(1, int(ray.cluster_resources().get("CPU", 2)) - 1)


def train(config: TrainConfig) -> dict:
    task = make_task(config.shape, config.pieces, config.removal, resolution=config.resolution)
    check_fits(task, config.net())
    logdir = Path(config.logdir)
    if (logdir / "checkpoints").exists():
        raise RLLockError(f"{logdir} already holds a training run; choose another --logdir")
    logdir.mkdir(parents=True, exist_ok=True)
    (logdir / "config.json").write_text(json.dumps(asdict(config), indent=1))
    writer = SummaryWriter(str(logdir))
    writer.add_text("config", "```\n" + json.dumps(asdict(config), indent=1) + "\n```", 0)
    latest_mngr = ckpt.manager(logdir / "checkpoints", keep=3)
    best_mngr = ckpt.manager(logdir / "best", keep=1)
    learner = Learner(task, config.net(), config.learner(), jax.random.PRNGKey(config.seed))
    validator = Validator(Searcher(PolicyValueNet(config.net()), config.mcts(), config.canvas, task.piece_size,
                                   config.validation_episodes), task, config)
    started_ray = _start_ray(config)
    try:
        return _loop(config, task, learner, validator, writer, latest_mngr, best_mngr, logdir)
    finally:
        writer.close()
        latest_mngr.close()
        best_mngr.close()
        if started_ray:
            ray.shutdown()


def _loop(config, task, learner, validator, writer, latest_mngr, best_mngr, logdir) -> dict:
    spec = TaskSpec.of(task)
    play_config = SelfPlayConfig(config.episodes_per_batch, config.mcts(), config.net())
    buffer = ray.remote(num_cpus=0)(ReplayBuffer).remote(
        config.buffer_capacity, task.size, config.candidates, task.piece_size)
    n_actors = _actor_count(config)
    actors = [SelfPlayActor.options(runtime_env={"env_vars": ACTOR_ENV}).remote(
        spec, play_config, config.seed * 1000 + i + 1, buffer) for i in range(n_actors)]
    log.info("training %s K=%d with %d self-play actor(s) for %g min; logs in %s", task.shape_name,
             task.pieces, n_actors, config.minutes, logdir)
    version = 0
    weights = [ray.put(jax.device_get(learner.params))]
    inflight = {actor.run.remote(weights, version): actor for actor in actors}
    start = time.monotonic()
    deadline = start + 60 * config.minutes
    episodes = successes = simulations = transitions = 0
    next_validate = start + 60 * config.validate_minutes
    next_checkpoint = start + 60 * config.checkpoint_minutes
    next_report = start + 30
    best_rate, last_score = -1.0, None
    lag = 0
    while time.monotonic() < deadline:
        can_learn = transitions >= config.min_buffer and (
            (learner.step + 1) * config.batch_size <= config.replay_ratio * transitions)
        ready, _ = ray.wait(list(inflight), num_returns=1, timeout=0 if can_learn else 1.0)
        for ref in ready:
            actor = inflight.pop(ref)
            stats = ray.get(ref)
            episodes += stats.episodes
            successes += stats.successes
            simulations += stats.simulations
            lag = version - stats.version
            transitions = ray.get(buffer.stats.remote())["added"]
            inflight[actor.run.remote(weights, version)] = actor
        if can_learn:
            sample = ray.get(buffer.sample.remote(config.batch_size, config.seed * 7919 + learner.step))
            losses = learner.update(sample)
            if learner.step % config.publish_every == 0:
                version += 1
                weights = [ray.put(jax.device_get(learner.params))]
            if learner.step % 10 == 0:
                writer.add_scalar("losses/policy", losses["policy"], learner.step)
                writer.add_scalar("losses/value", losses["value"], learner.step)
                writer.add_scalar("losses/total", losses["policy"] + losses["value"], learner.step)
        now = time.monotonic()
        if now >= next_report or ready:
            elapsed = now - start
            writer.add_scalar("charts/episodes_per_sec", episodes / elapsed, learner.step)
            writer.add_scalar("charts/simulations_per_sec", simulations / elapsed, learner.step)
            writer.add_scalar("charts/learner_steps_per_sec", learner.step / elapsed, learner.step)
            writer.add_scalar("charts/policy_lag", lag, learner.step)
            writer.add_scalar("charts/selfplay_success_rate", successes / max(episodes, 1), learner.step)
            writer.add_scalar("buffer/size", min(transitions, config.buffer_capacity), learner.step)
        if now >= next_report:
            log.info("step %d | episodes %d | self-play success %.1f%% | validation %s | %.0f s", learner.step,
                     episodes, 100 * successes / max(episodes, 1),
                     "-" if last_score is None else f"{100 * last_score['success_rate']:.1f}%", now - start)
            next_report = now + 30
        if now >= next_checkpoint:
            ckpt.save(latest_mngr, learner.step, learner.state(), checkpoint_meta(config, task, learner.step, last_score))
            next_checkpoint = now + 60 * config.checkpoint_minutes
        if now >= next_validate:
            last_score, best_rate = _validate(config, task, learner, validator, writer, best_mngr, best_rate)
            next_validate = time.monotonic() + 60 * config.validate_minutes
    for stats in ray.get(list(inflight)):  # batches under way finish before the final evaluation
        episodes += stats.episodes
        successes += stats.successes
        simulations += stats.simulations
    last_score, best_rate = _validate(config, task, learner, validator, writer, best_mngr, best_rate)
    ckpt.save(latest_mngr, learner.step, learner.state(), checkpoint_meta(config, task, learner.step, last_score))
    elapsed = time.monotonic() - start
    return {"steps": learner.step, "episodes": episodes, "selfplay_success_rate": successes / max(episodes, 1),
            "validation": last_score, "best_success_rate": best_rate, "seconds": elapsed,
            "episodes_per_sec": episodes / elapsed, "simulations_per_sec": simulations / elapsed,
            "actors": len(inflight), "logdir": str(logdir)}


def _validate(config, task, learner, validator, writer, best_mngr, best_rate):
    score = validator(learner.params)
    writer.add_scalar("validation/success_rate", score["success_rate"], learner.step)
    if score["time_per_valid_s"] is not None:
        writer.add_scalar("validation/time_per_valid_s", score["time_per_valid_s"], learner.step)
    log.info("validation at step %d: %d/%d valid (%.1f%%)", learner.step, score["valid"], score["episodes"],
             100 * score["success_rate"])
    if score["success_rate"] > best_rate or best_mngr.latest_step() is None:
        ckpt.save(best_mngr, learner.step, learner.state(), checkpoint_meta(config, task, learner.step, score))
        best_rate = max(best_rate, score["success_rate"])
    return score, best_rate
