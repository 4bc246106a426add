"""Batched inference from a checkpoint: the paper's protocol (batches of episodes until C valid
assemblies or the time limit), every result verified before it is written."""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import jax
from tqdm import tqdm

from learner.learner import Learner, LearnerConfig
from rllock import checkpoint as ckpt
from rllock.assembly import write_assembly
from rllock.env import Task, assembly_key, final_labels
from rllock.mcts import MCTSConfig, Searcher, play
from rllock.network import NetConfig, PolicyValueNet

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Policy:
    """A network and the search settings it was trained with, for one task."""

    task: Task
    net: NetConfig
    mcts: MCTSConfig
    params: dict
    source: str  # checkpoint path, or "untrained (seed N)"
    step: int


def _configs(meta: dict) -> tuple[NetConfig, MCTSConfig, LearnerConfig]:
    net = meta["net"]
    return (NetConfig(canvas=net["canvas"], features=tuple(net["features"]), value_hidden=net["value_hidden"]),
            MCTSConfig(**meta["mcts"]), LearnerConfig(**meta["learner"]))


def load_policy(path: str | Path, expect: dict | None = None) -> Policy:
    """The policy in a checkpoint (a run's log directory: its best checkpoint). `expect`: a task identity
    the checkpoint must match."""
    step_dir = ckpt.find_step_dir(Path(path))
    meta = ckpt.read_meta(step_dir)
    if expect is not None:
        ckpt.check_same_task(meta["task"], expect, step_dir)
    task = ckpt.task_from_identity(meta["task"])
    net, mcts, learner_config = _configs(meta)
    state = ckpt.restore_like(step_dir, Learner(task, net, learner_config, jax.random.PRNGKey(0)).state())
    return Policy(task, net, mcts, state["params"], str(step_dir), int(state["step"]))


def untrained_like(policy: Policy, seed: int) -> Policy:
    """The same network and search with freshly initialised weights: the baseline learning must beat."""
    from rllock.network import init_params

    return Policy(policy.task, policy.net, policy.mcts, init_params(policy.net, jax.random.PRNGKey(seed)),
                  f"untrained (seed {seed})", 0)


@dataclass(frozen=True)
class GenerateResult:
    valid: int
    episodes: int
    seconds: float
    time_per_valid_s: float | None

    @property
    def success_rate(self) -> float:
        return self.valid / max(self.episodes, 1)


def generate(policy: Policy, *, count: int, batch: int, time_limit: float, seed: int,
             out: Path | None = None, progress: bool = True) -> GenerateResult:
    """Batches of `batch` lockstep episodes until `count` distinct valid assemblies or `time_limit`
    seconds (a batch that has started finishes). Writes each one under `out` when given."""
    task = policy.task
    searcher = Searcher(PolicyValueNet(policy.net), policy.mcts, policy.net.canvas, task.piece_size, batch)
    key = jax.random.PRNGKey(seed)
    seen: set[bytes] = set()
    episodes = 0
    start = time.perf_counter()
    with tqdm(total=count, desc=f"generate {task.shape_name} K={task.pieces}", unit="assembly",
              disable=None if progress else True) as bar:
        round_ = 0
        while len(seen) < count and time.perf_counter() - start < time_limit:
            key, sub = jax.random.split(key)
            t0 = time.perf_counter()
            results = play(searcher, policy.params, task, sub, batch=batch, seed=seed * 100_003 + round_,
                           canvas=policy.net.canvas)
            round_ += 1
            episodes += len(results)
            for episode in results:
                if not episode.success or len(seen) >= count:
                    continue
                labels = final_labels(task, episode.final)
                key_bytes = assembly_key(labels)
                if key_bytes in seen:
                    continue
                seen.add(key_bytes)
                bar.update(1)
                if out is not None:
                    write_assembly(out / f"assembly_{len(seen):03d}", task.topology.to_grid(labels),
                                   removal=task.removal, shape=task.shape_name,
                                   method={"name": "rl-lock", "checkpoint": policy.source, "step": policy.step,
                                           "batch": batch, **asdict(policy.mcts)},
                                   seed=seed, timings={"batch_seconds": round(time.perf_counter() - t0, 3)})
    seconds = time.perf_counter() - start
    return GenerateResult(len(seen), episodes, seconds, seconds / len(seen) if seen else None)
