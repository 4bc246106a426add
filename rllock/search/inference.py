"""Batched inference from a checkpoint: the paper's protocol (batches of episodes until C valid
assemblies or the time limit), every result verified before it is written.

Round r of a protocol with seed s plays one batch with PRNG key fold_in(key(s), r) and node seed
derive_seed(s, r), split into lockstep groups searched in threads (`local_groups`: one per core on a
CPU, one on a GPU; one per Ray actor of one core in `rllock.orchestration.generate`). The same seed and group
count give the same episodes; on Ray, which rounds finish first also decides which assemblies are kept.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import jax
from tqdm import tqdm

from rllock.config import MCTSConfig, NetConfig
from rllock.core.env import Task, assembly_key, final_labels
from rllock.errors import RLLockError
from rllock.files import checkpoint as ckpt
from rllock.files.assembly import PictureWriter, write_assembly
from rllock.files.orbax_io import restore_like
from rllock.search.base import Episode, Player, derive_seed
from rllock.search.mcts import play_groups
from rllock.search.methods import players
from rllock.search.network import init_params, params_template
from rllock.search.serving import Wanted, served

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Policy:
    """A network and the search settings it was trained with, for one task."""

    task: Task
    net: NetConfig  # with a concrete canvas
    mcts: MCTSConfig
    method: str  # rllock.config.METHODS: what one search action is
    params: dict
    source: str  # checkpoint path, or "untrained (seed N)"
    step: int


def load_network(source: str | Path | ckpt.Checkpoint) -> tuple[ckpt.Checkpoint, NetConfig, dict]:
    """(checkpoint, network config, parameters) of a checkpoint (a run's log directory: its best
    checkpoint; a step directory; a shipped name; or one already opened). Only the parameters are read,
    against a template from `jax.eval_shape`."""
    checkpoint = ckpt.open_checkpoint(source)
    net = checkpoint.metadata.config.net
    params = restore_like(checkpoint.step_dir, {"params": params_template(net)}, partial=True)["params"]
    return checkpoint, net, params


def load_policy(source: str | Path | ckpt.Checkpoint, wanted: Wanted = None) -> Policy:
    """The policy in a checkpoint (a run's log directory: its best checkpoint; a shipped name; or a
    checkpoint already opened) for `wanted` (`rllock.search.serving.served`: a single-task checkpoint's
    own task, checked against `wanted` when given; a multi-task checkpoint's `wanted`, on the canvas it
    plays it on)."""
    checkpoint, net, params = load_network(source)
    meta, step_dir = checkpoint.metadata, checkpoint.step_dir
    task, canvas = served(meta, step_dir, wanted)
    if canvas not in meta.canvases:
        trained = meta.canvases
        log.info(
            "%s was trained on %s; it plays %s on %d^3 (its weights fit any side)",
            source if isinstance(source, str) else step_dir,
            f"a {trained[0]}^3 canvas"
            if len(trained) == 1
            else ", ".join(f"{c}^3" for c in trained) + " canvases",
            task.shape_name,
            canvas,
        )
    net = dataclasses.replace(net, canvas=canvas)
    return Policy(task, net, meta.config.mcts, meta.config.method, params, str(step_dir), meta.step)


def check_simulations(simulations: int | None) -> None:
    if simulations is not None and simulations < 1:
        raise RLLockError(f"--simulations must be at least 1, got {simulations}")


def with_simulations(policy: Policy, simulations: int | None) -> Policy:
    """`policy` searching with `simulations` per decision (None: the number it was trained with). More
    simulations cost proportionally more per batch and can find far more valid assemblies per episode
    than the training budget does."""
    if simulations is None:
        return policy
    if policy.method == "ppo":
        raise RLLockError("--simulations: a ppo checkpoint runs no search")
    check_simulations(simulations)
    return dataclasses.replace(policy, mcts=dataclasses.replace(policy.mcts, simulations=simulations))


def untrained_like(policy: Policy, seed: int) -> Policy:
    """The same network and search with freshly initialised weights: the baseline learning must beat."""
    return Policy(
        policy.task,
        policy.net,
        policy.mcts,
        policy.method,
        init_params(policy.net, jax.random.PRNGKey(seed)),
        f"untrained (seed {seed})",
        0,
    )


def local_groups() -> int:
    """Lockstep groups for a batch in this process: one per core on a CPU, where the groups' samplers
    and networks overlap (`mcts.play_groups`); one on a GPU, which wants the whole batch at once."""
    return (os.cpu_count() or 1) if jax.default_backend() == "cpu" else 1


def searchers_for(policy: Policy, batch: int, groups: int) -> Sequence[Player]:
    return players(policy.method, policy.net, policy.mcts, policy.task, batch, groups)


def play_round(group_searchers: Sequence[Player], policy: Policy, seed: int, round_: int) -> list[Episode]:
    """Round `round_` of the protocol with seed `seed` (module docstring)."""
    key = jax.random.fold_in(jax.random.PRNGKey(seed), round_)
    return play_groups(group_searchers, policy.params, policy.task, key, seed=derive_seed(seed, round_))


@dataclass(frozen=True)
class GenerateResult:
    valid: int
    episodes: int
    seconds: float
    time_per_valid_s: float | None
    best_placed: int = 0  # the most pieces any episode placed (K - 1 in a valid one)

    @property
    def success_rate(self) -> float:
        return self.valid / max(self.episodes, 1)


class Collector:
    """Keeps the distinct valid assemblies of finished rounds, up to `count`, and writes each (verified)
    under `out` when given."""

    def __init__(
        self,
        policy: Policy,
        *,
        count: int,
        batch: int,
        seed: int,
        out: Path | None,
        picture: PictureWriter | None,
        progress: bool,
    ):
        self.policy, self.count, self.batch, self.seed, self.out, self.picture = (
            policy,
            count,
            batch,
            seed,
            out,
            picture,
        )
        self.seen: set[bytes] = set()
        self.episodes = 0
        self.best_placed = 0
        task = policy.task
        self.bar = tqdm(
            total=count,
            desc=f"generate {task.shape_name} K={task.pieces}",
            unit="assembly",
            disable=None if progress else True,
        )

    @property
    def done(self) -> bool:
        return len(self.seen) >= self.count

    def take(self, episodes: list[Episode], batch_seconds: float) -> None:
        task = self.policy.task
        self.episodes += len(episodes)
        self.best_placed = max([self.best_placed, *(e.final.placed for e in episodes)])
        best = f"best {self.best_placed} of {task.pieces - 1} placed"
        self.bar.set_postfix_str(f"{self.episodes} episodes, {best}", refresh=False)
        for episode in episodes:
            if not episode.success or self.done:
                continue
            labels = final_labels(task, episode.final)
            key = assembly_key(labels)
            if key in self.seen:
                continue
            self.seen.add(key)
            self.bar.update(1)
            if self.out is not None:
                write_assembly(
                    self.out / f"assembly_{len(self.seen):03d}",
                    task.topology.to_grid(labels),
                    removal=task.removal,
                    shape=task.shape_name,
                    method={
                        "name": self.policy.method,
                        "checkpoint": self.policy.source,
                        "step": self.policy.step,
                        "batch": self.batch,
                        # PPO samples from the policy at temperature 1: it has no search settings.
                        **({"temperature": 1.0} if self.policy.method == "ppo" else asdict(self.policy.mcts)),
                    },
                    seed=self.seed,
                    timings={"batch_seconds": round(batch_seconds, 3)},
                    picture=self.picture,
                )

    def result(self, seconds: float) -> GenerateResult:
        self.bar.close()
        valid = len(self.seen)
        per_valid = seconds / valid if valid else None
        return GenerateResult(valid, self.episodes, seconds, per_valid, self.best_placed)


def generate(
    policy: Policy,
    *,
    count: int,
    batch: int,
    time_limit: float,
    seed: int,
    out: Path | None = None,
    picture: PictureWriter | None = None,
    progress: bool = True,
    stop: Callable[[], bool] = lambda: False,
    report: Callable[[int, int, int], None] | None = None,
    searchers: Sequence[Player] | None = None,
) -> GenerateResult:
    """Rounds of `batch` lockstep episodes until `count` distinct valid assemblies, `time_limit`
    seconds or `stop()` (a round that has started finishes), in this process. `report(episodes, valid,
    most pieces placed)` after each round; `searchers`: the lockstep groups to play (default: the
    policy's own network, one group per core)."""
    start = time.perf_counter()
    group_searchers = searchers_for(policy, batch, local_groups()) if searchers is None else searchers
    collector = Collector(
        policy, count=count, batch=batch, seed=seed, out=out, picture=picture, progress=progress
    )
    round_ = 0
    while not collector.done and time.perf_counter() - start < time_limit and not stop():
        t0 = time.perf_counter()
        collector.take(play_round(group_searchers, policy, seed, round_), time.perf_counter() - t0)
        round_ += 1
        if report is not None:
            report(collector.episodes, len(collector.seen), collector.best_placed)
    return collector.result(time.perf_counter() - start)


@dataclass(frozen=True)
class SuccessRate:
    valid: int  # successful episodes (duplicates counted: a rate, like training's validation)
    episodes: int
    seconds: float

    @property
    def rate(self) -> float:
        return self.valid / max(self.episodes, 1)

    def interval(self, z: float = 1.96) -> tuple[float, float]:
        """Wilson's score interval for the rate (95% by default), sound near 0 and 1 too."""
        n = max(self.episodes, 1)
        p = self.valid / n
        centre = (p + z * z / (2 * n)) / (1 + z * z / n)
        half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
        return max(centre - half, 0.0), min(centre + half, 1.0)


def success_rate(policy: Policy, *, episodes: int, batch: int, seed: int) -> SuccessRate:
    """The fraction of valid episodes over rounds 0.. of the protocol with `seed` (`play_round`), at least
    `episodes` in all: a validation far larger than training's, with the same seeds for every policy."""
    for flag, value in (("--episodes", episodes), ("--batch", batch)):
        if value < 1:
            raise RLLockError(f"{flag} must be at least 1, got {value}")
    start = time.perf_counter()
    group_searchers = searchers_for(policy, batch, local_groups())
    valid = played = round_ = 0
    with tqdm(total=episodes, desc="episodes", unit="episode", disable=None) as bar:
        while played < episodes:
            played_now = play_round(group_searchers, policy, seed, round_)
            valid += sum(e.success for e in played_now)
            played += len(played_now)
            bar.update(len(played_now))
            round_ += 1
    return SuccessRate(valid, played, time.perf_counter() - start)
