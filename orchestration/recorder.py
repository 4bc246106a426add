"""What a training run leaves on disk: TensorBoard events, orbax checkpoints (latest and best), and the
best validation assembly with its picture."""

from __future__ import annotations

import dataclasses
import json
import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from PIL import Image
from tensorboardX import SummaryWriter

from rllock.config import TrainConfig, to_json
from rllock.core.env import Task
from rllock.files import checkpoint as ckpt
from rllock.files import orbax_io
from rllock.files.assembly import write_assembly
from rllock.files.provenance import portable, provenance
from rllock.files.render import write_picture

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


def validation_rank(score: dict | None) -> tuple[float, float]:
    """How validations compare: success rate first, then the mean return (how far the episodes got),
    so that a hard task where no validation succeeds yet still keeps its most promising checkpoint."""
    score = score or {}
    return float(score.get("success_rate", -1.0)), float(score.get("mean_return", -1.0))


def best_rank(logdir: Path) -> tuple[float, float]:
    """The validation rank of the run's best checkpoint ((-1, -1) when there is none yet)."""
    steps = ckpt.saved_steps(logdir / "best")
    if not steps:
        return -1.0, -1.0
    return validation_rank(ckpt.read_metadata(logdir / "best" / str(steps[-1])).validation)


class Recorder:
    def __init__(
        self,
        logdir: Path,
        config: TrainConfig,
        task: Task | dict,
        step: int,
        resume: bool,
        sessions: list[dict],
    ):
        """`task`: the run's task, or a multi-task run's identity (`checkpoint.Metadata.of`); `sessions`:
        the provenance of the processes that trained this run before (when resumed). The metadata names
        the log directory as `checkpoint.portable` does: a checkpoint carries no machine's paths."""
        self.logdir, self.task = logdir, task
        self.config = dataclasses.replace(config, logdir=portable(config.logdir))
        self.sessions = [*sessions, provenance()]
        logdir.mkdir(parents=True, exist_ok=True)
        # purge_step drops events logged after the checkpoint we resume from, so the curves do not fork.
        self.writer = SummaryWriter(str(logdir), purge_step=step if resume else None)
        self.writer.add_text("config", "```\n" + json.dumps(to_json(config), indent=1) + "\n```", step)
        self.latest = orbax_io.manager(logdir / "checkpoints", keep=3)
        self.best = orbax_io.manager(logdir / "best", keep=1)

    def scalars(self, values: dict[str, float], step: int) -> None:
        for tag, value in values.items():
            self.writer.add_scalar(tag, value, step)

    def checkpoint(self, step: int, state, validation: dict | None, counters: Counters) -> None:
        orbax_io.save(
            self.latest,
            step,
            state,
            ckpt.Metadata.of(
                self.config, self.task, step, validation, asdict(counters), self.sessions
            ).to_json(),
        )

    def best_checkpoint(
        self,
        step: int,
        state,
        validation: dict,
        counters: Counters,
        assembly: tuple[Task, np.ndarray] | None,
    ) -> None:
        """`assembly`: a valid assembly of the validation (its task and labels grid) to keep beside it."""
        orbax_io.save(
            self.best,
            step,
            state,
            ckpt.Metadata.of(
                self.config, self.task, step, validation, asdict(counters), self.sessions
            ).to_json(),
        )
        if assembly is not None:
            self._best_assembly(*assembly, step)

    def _best_assembly(self, task: Task, grid: np.ndarray, step: int) -> None:
        folder = self.logdir / "best_assembly"
        png = folder / "assembly.png"
        png.unlink(missing_ok=True)  # never leave the previous best's picture beside the new assembly
        write_assembly(
            folder,
            grid,
            removal=task.removal,
            shape=task.shape_name,
            method={"name": "rl-lock validation", "step": step},
            seed=self.config.seed,
            timings={},
            picture=write_picture,
        )
        self.writer.add_image(
            "best/assembly", np.asarray(Image.open(png).convert("RGB")), step, dataformats="HWC"
        )

    def close(self) -> None:
        self.writer.close()
        self.latest.close()
        self.best.close()
