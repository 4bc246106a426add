"""What a training run leaves on disk, for both trainers: TensorBoard events, orbax checkpoints (the
latest few; a policy run also its best validated one, with that validation's assembly and picture), and
the counters every checkpoint keeps so that a resumed run goes on counting."""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Protocol, TypeVar

import numpy as np
from PIL import Image
from tensorboardX import SummaryWriter

from rllock.config import to_json
from rllock.core.env import Task
from rllock.files import checkpoint as ckpt
from rllock.files import orbax_io
from rllock.files.assembly import write_assembly
from rllock.files.provenance import portable, provenance
from rllock.files.render import write_picture
from rllock.search.guide_checkpoint import guide_metadata

log = logging.getLogger(__name__)


class Totals(Protocol):
    """What a trainer's actors have reported in all (`rllock.actors.selfplay.PlayTotals`,
    `rllock.actors.guide_actor.SearchTotals`): a dataclass, whose fields every checkpoint keeps."""

    __dataclass_fields__: ClassVar[dict[str, Any]]

    def add(self, report: Any) -> None: ...

    @property
    def produced(self) -> int:
        """Items pushed into the replay buffer in all: what the replay ratio divides by."""
        ...


T = TypeVar("T", bound=Totals)


def totals_of(kind: type[T], doc: dict) -> T:
    """The totals of type `kind` that a checkpoint's counters hold (a field it lacks: its default)."""
    return kind(**{f.name: doc[f.name] for f in dataclasses.fields(kind) if f.name in doc})


@dataclass
class Counters:
    """Run totals that survive a resume, saved flat in every checkpoint's metadata: the actors' (`totals`),
    the seconds trained, the weights version handed out last and, in a run that validates, the best
    validation's rank (success rate, then mean return: `validation_rank`), the bar a new best must pass."""

    totals: Totals | None = None  # None: no actors counted (a validation on its own)
    seconds: float = 0.0
    version: int = 0
    best: tuple[float, float] | None = None  # None: a run that does not validate

    def add(self, report: Any) -> None:
        assert self.totals is not None, "a run with actors has their totals"
        self.totals.add(report)

    @property
    def produced(self) -> int:
        return 0 if self.totals is None else self.totals.produced

    def to_json(self) -> dict:
        doc = {} if self.totals is None else dataclasses.asdict(self.totals)
        doc |= {"seconds": self.seconds, "version": self.version}
        if self.best is not None:
            doc |= {"best_rate": self.best[0], "best_return": self.best[1]}
        return doc

    @staticmethod
    def of(doc: dict, totals: Totals | None, *, validates: bool = False) -> Counters:
        """The counters a checkpoint's metadata holds (`to_json`), with `totals` read from it."""
        best = None
        if validates:
            best = (float(doc.get("best_rate", -1.0)), float(doc.get("best_return", -1.0)))
        return Counters(totals, float(doc.get("seconds", 0.0)), int(doc.get("version", 0)), best)


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
        config: Any,
        task: Task | dict | None,
        step: int,
        resume: bool,
        sessions: list[dict],
        extra: dict | None = None,
    ):
        """`config`: the run's config. `task`: a policy run's task, or a multi-task run's identity
        (`checkpoint.Metadata.of`); None for a guide run, which learns no task: its checkpoints are guide
        checkpoints (`rllock.search.guide_checkpoint`) and it keeps no best one. `sessions`: the
        provenance of the processes that trained this run before (when resumed); `extra`: what else every
        checkpoint's metadata records (the snapshots an offline guide learned from). A policy run's
        metadata names the log directory as `checkpoint.portable` does: a checkpoint carries no
        machine's paths, and TensorBoard shows its config."""
        self.logdir, self.task, self.config, self.extra = logdir, task, config, extra or {}
        self.sessions = [*sessions, provenance()]
        logdir.mkdir(parents=True, exist_ok=True)
        # purge_step drops events logged after the checkpoint we resume from, so the curves do not fork.
        self.writer = SummaryWriter(str(logdir), purge_step=step if resume else None)
        if task is not None:
            self.config = dataclasses.replace(config, logdir=portable(config.logdir))
            self.writer.add_text("config", "```\n" + json.dumps(to_json(config), indent=1) + "\n```", step)
        self.latest = orbax_io.manager(logdir / "checkpoints", keep=3)
        self.best = None if task is None else orbax_io.manager(logdir / "best", keep=1)

    def scalars(self, values: Mapping[str, float], step: int) -> None:
        for tag, value in values.items():
            self.writer.add_scalar(tag, value, step)

    def metadata(self, step: int, validation: dict | None, counters: Counters) -> dict:
        """A checkpoint's metadata document: a policy checkpoint's or a guide checkpoint's."""
        counted = counters.to_json()
        if self.task is None:
            return guide_metadata(self.config, step, counted, self.sessions) | self.extra
        meta = ckpt.Metadata.of(self.config, self.task, step, validation, counted, self.sessions)
        return meta.to_json() | self.extra

    def checkpoint(self, step: int, state: Any, validation: dict | None, counters: Counters) -> None:
        orbax_io.save(self.latest, step, state, self.metadata(step, validation, counters))

    def has_best(self) -> bool:
        return self.best is not None and self.best.latest_step() is not None

    def best_checkpoint(
        self,
        step: int,
        state: Any,
        validation: dict,
        counters: Counters,
        assembly: tuple[Task, np.ndarray] | None,
    ) -> None:
        """`assembly`: a valid assembly of the validation (its task and labels grid) to keep beside it."""
        assert self.best is not None, "a policy run keeps its best checkpoint"
        orbax_io.save(self.best, step, state, self.metadata(step, validation, counters))
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

    def flush(self) -> None:
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()
        self.latest.close()
        if self.best is not None:
            self.best.close()
