"""Validation of a training run: what it plays, playing it, its score, and keeping the best checkpoint.

Every validation of a run plays the same fixed tasks from the same seeds, so that scores compare across
learner steps: the run's task, or one fixed task per group of a multi-task run, each in one lockstep
group in the driver beside the learner. `play` runs the searches and `keep_best` writes the best
checkpoint; the rest is pure.
"""

from __future__ import annotations

import dataclasses
import logging
import re
from collections.abc import Sequence
from dataclasses import dataclass, replace

import jax
import numpy as np

from rllock.actors.selfplay import evaluate
from rllock.config import TrainConfig
from rllock.core.env import Task, final_labels
from rllock.learner.learner import Learner
from rllock.orchestration.pacing import validation_estimate
from rllock.orchestration.pool import Layout
from rllock.orchestration.recorder import Counters, Recorder, validation_rank
from rllock.search.base import Episode, Player
from rllock.search.methods import players
from rllock.search.workload import Workload

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Plan:
    """What every validation of a run plays."""

    tasks: tuple[Task, ...]
    # per task: one lockstep group of `episodes` episodes, compiled once
    searchers: tuple[Sequence[Player], ...]
    episodes: int  # per task
    seed: int  # the key and the episodes' seeds, the same at every validation
    groups: tuple[str, ...] | None  # multi-task runs: each task's group, as written in --tasks

    @staticmethod
    def of(config: TrainConfig, workload: Workload) -> Plan:
        seed = config.seed + 7
        draws = workload.validation(seed)
        return Plan(
            tasks=tuple(d.task for d in draws),
            searchers=tuple(
                players(
                    config.method,
                    replace(config.net, canvas=d.canvas),
                    config.mcts,
                    d.task,
                    config.validation_episodes,
                    1,
                )
                for d in draws
            ),
            episodes=config.validation_episodes,
            seed=seed,
            groups=tuple(d.label for d in draws if d.label is not None) or None,
        )

    @property
    def total_episodes(self) -> int:
        return self.episodes * len(self.tasks)


@dataclass(frozen=True)
class Score:
    """A validation's score, as checkpoint metadata keeps it (`to_json`): success rate and mean return
    (means over the tasks), valid episodes, episodes, seconds, seconds per valid one (None when none was
    valid) and, in a multi-task run, each group's own score by its spec, with its task (`task_score`)."""

    success_rate: float
    valid: int
    episodes: int
    mean_return: float
    seconds: float
    time_per_valid_s: float | None
    groups: dict[str, dict] | None = None

    def to_json(self) -> dict:
        doc = dataclasses.asdict(self)
        return doc if self.groups is not None else {k: v for k, v in doc.items() if k != "groups"}

    @staticmethod
    def from_json(doc: dict) -> Score:
        return Score(
            float(doc.get("success_rate", 0.0)),
            int(doc.get("valid", 0)),
            int(doc.get("episodes", 0)),
            float(doc.get("mean_return", 0.0)),
            float(doc.get("seconds", 0.0)),
            doc.get("time_per_valid_s"),
            doc.get("groups"),
        )

    def rank(self) -> tuple[float, float]:
        return validation_rank(self.to_json())


@dataclass(frozen=True)
class Result:
    score: Score
    first_win: tuple[Task, Episode] | None
    """The first valid episode with its task: the assembly kept beside a best checkpoint."""


def play(plan: Plan, params) -> list[tuple[list[Episode], float]]:
    """Each task's episodes and the seconds they took."""
    return [
        evaluate(searchers, params, task, jax.random.PRNGKey(plan.seed), seed=plan.seed)
        for task, searchers in zip(plan.tasks, plan.searchers)
    ]


def task_score(task: Task, episodes: list[Episode], seconds: float) -> dict:
    valid = len([e for e in episodes if e.success])
    return {
        "task": f"{task.shape_name} K={task.pieces}",
        "success_rate": valid / len(episodes),
        "valid": valid,
        "episodes": len(episodes),
        "mean_return": float(np.mean([e.final.placed for e in episodes])) / task.pieces,
        "seconds": seconds,
    }


def summarize(plan: Plan, played: list[tuple[list[Episode], float]]) -> Result:
    """The validation's result from what `play` returned."""
    scores = [task_score(task, episodes, seconds) for task, (episodes, seconds) in zip(plan.tasks, played)]
    valid = sum(s["valid"] for s in scores)
    seconds = sum(s["seconds"] for s in scores)
    score = Score(
        success_rate=float(np.mean([s["success_rate"] for s in scores])),
        valid=valid,
        episodes=sum(s["episodes"] for s in scores),
        mean_return=float(np.mean([s["mean_return"] for s in scores])),
        seconds=seconds,
        time_per_valid_s=seconds / valid if valid else None,
        groups=None if plan.groups is None else dict(zip(plan.groups, scores)),
    )
    wins = ((task, e) for task, (episodes, _) in zip(plan.tasks, played) for e in episodes if e.success)
    return Result(score, next(wins, None))


def scalars(score: Score) -> dict[str, float]:
    """The TensorBoard scalars of a validation: each group's (multi-task runs), then the means."""
    values = {}
    for group, s in (score.groups or {}).items():
        tag = re.sub(r"[^\w.\-]", "_", group)  # TensorBoard's tag characters: cube4_6-9
        values[f"validation/{tag}/success_rate"] = s["success_rate"]
        values[f"validation/{tag}/mean_return"] = s["mean_return"]
    values["validation/success_rate"] = score.success_rate
    values["validation/mean_return"] = score.mean_return
    if score.time_per_valid_s is not None:
        values["validation/time_per_valid_s"] = score.time_per_valid_s
    return values


def assembly(win: tuple[Task, Episode] | None) -> tuple[Task, np.ndarray] | None:
    """The task and labels grid of a valid episode's assembly."""
    if win is None:
        return None
    task, episode = win
    return task, task.topology.to_grid(final_labels(task, episode.final))


def keep_best(result: Result, learner: Learner, recorder: Recorder, counters: Counters) -> None:
    """Save `learner` as the best checkpoint, with the first valid assembly, when the validation ranks
    above the best so far (`recorder.validation_rank`) or there is no best checkpoint yet; the bar in
    `counters` never drops."""
    best, rank = counters.best or (-1.0, -1.0), result.score.rank()
    if rank > best or not recorder.has_best():
        counters.best = max(rank, best)
        recorder.best_checkpoint(
            learner.step, learner.state(), result.score.to_json(), counters, assembly(result.first_win)
        )


class Validator:
    """A run's validations: what one is expected to cost, playing it, its scalars, log line and best
    checkpoint. `last` is the latest score (a resumed run's, until it validates)."""

    def __init__(self, plan: Plan, last: Score | None):
        self.plan, self.last = plan, last
        self.seconds: float | None = None  # the last validation's own time

    def estimate(self, batch_seconds: float | None, layout: Layout) -> float | None:
        """Expected seconds of the next validation (`pacing.validation_estimate`)."""
        return validation_estimate(
            batch_seconds, layout.episodes, layout.groups, self.plan.total_episodes, self.seconds
        )

    def run(self, learner: Learner, recorder: Recorder, counters: Counters) -> Score:
        result = summarize(self.plan, play(self.plan, learner.params))
        score = self.last = result.score
        self.seconds = score.seconds
        recorder.scalars(scalars(score), learner.step)
        log.info(
            "validation at step %d: %d/%d valid (%.1f%%) in %.0f s",
            learner.step,
            score.valid,
            score.episodes,
            100 * score.success_rate,
            score.seconds,
        )
        keep_best(result, learner, recorder, counters)
        return score
