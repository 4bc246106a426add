"""A checkpoint's metadata, and finding checkpoints: run folders, step directories, shipped names.

A training run's log directory holds `checkpoints/<step>/` (the latest few) and `best/<step>/` (the
checkpoint with the best validation success rate). Each step directory has `state/` (params, optimizer
state, step, PRNG key: read and written by `rllock.files.orbax_io`) and `meta/metadata` (JSON): the task
identity, the run's whole config (the one document that both `--resume` and `generate` read), the
validation score and the run's counters. That document is read and written only here, as a typed
`Metadata`; `open_checkpoint` finds a step directory and reads it once.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

from rllock.config import TrainConfig, from_flat, from_json, to_json
from rllock.core.env import Task
from rllock.core.identity import task_identity
from rllock.errors import RLLockError

log = logging.getLogger(__name__)

FORMAT = "rllock-checkpoint"
META_VERSION = 2
# Trained checkpoints shipped inside the package (see rllock.search.pretrained), reached by name.
SHIPPED = Path(__file__).resolve().parents[1] / "checkpoints"
SHIPPED_NAME = re.compile(r"^[a-z][a-z0-9]*(-k[0-9]+)?$")
T = TypeVar("T")


def shipped_names(folder: Path | None = None) -> list[str]:
    """The names of the shipped checkpoints (in `folder`, default `SHIPPED`)."""
    folder = SHIPPED if folder is None else folder
    if not folder.is_dir():
        return []
    return sorted(p.name for p in folder.iterdir() if (p / "meta" / "metadata").is_file())


@dataclass(frozen=True)
class Metadata:
    """A checkpoint's metadata. `task` is its task identity: `task_identity` for a single-task run, or
    `rllock.core.tasks.TaskSet.identity` (with a "tasks" key) for a multi-task one; `config` the run's
    whole config, with a concrete canvas; `sessions` the `provenance` of each process that trained the
    run (one more per resume); `shipped`, for a checkpoint shipped in the package, where it came from."""

    step: int
    task: dict
    config: TrainConfig
    validation: dict | None = None
    counters: dict = field(default_factory=dict)
    sessions: tuple[dict, ...] = ()
    shipped: dict | None = None

    @property
    def multitask(self) -> bool:
        """Whether the network was trained for many tasks (`rllock train --tasks`)."""
        return "tasks" in self.task

    @property
    def canvas(self) -> int:
        return int(self.task["canvas"])

    @property
    def canvases(self) -> list[int]:
        """The canvas sides the network was trained on (a run before several canvases: its one)."""
        return [int(c) for c in self.task.get("canvases", [self.canvas])]

    @property
    def removal(self) -> str:
        return str(self.task["removal"])

    @staticmethod
    def of(
        config: TrainConfig,
        task: Task | dict,
        step: int,
        validation: dict | None = None,
        counters: dict | None = None,
        sessions: tuple[dict, ...] | list[dict] = (),
    ) -> Metadata:
        """The metadata of a run's checkpoint: `task` is the run's task (its identity is taken on the
        config's canvas) or a multi-task run's identity."""
        identity = task if isinstance(task, dict) else task_identity(task, config.net.canvas_side())
        return Metadata(step, identity, config, validation, counters or {}, tuple(sessions))

    def to_json(self) -> dict:
        doc = {
            "format": FORMAT,
            "version": META_VERSION,
            "step": self.step,
            "task": self.task,
            "config": to_json(self.config),
            "validation": self.validation,
            "counters": self.counters,
            "sessions": list(self.sessions),
        }
        return doc if self.shipped is None else {**doc, "shipped": self.shipped}

    @staticmethod
    def from_json(doc: dict) -> Metadata:
        """The metadata of `doc`, of this version or version 1 (which saved the run's settings flat, with
        the network's and the search's beside them)."""
        if "config" in doc:
            config = from_json(TrainConfig, doc["config"])
        else:
            config = from_flat(TrainConfig, {**doc["train"], **doc.get("net", {}), **doc.get("mcts", {})})
        return Metadata(
            step=int(doc["step"]),
            task=doc["task"],
            config=config,
            validation=doc.get("validation"),
            counters=doc.get("counters") or {},
            sessions=tuple(doc.get("sessions") or ()),
            shipped=doc.get("shipped"),
        )


@dataclass(frozen=True)
class Checkpoint:
    """A step directory and its metadata, read once."""

    step_dir: Path
    metadata: Metadata


def open_checkpoint(path: str | Path | Checkpoint) -> Checkpoint:
    """The checkpoint at `path` (see `find_step_dir`), its metadata read; a `Checkpoint` as it is."""
    if isinstance(path, Checkpoint):
        return path
    step_dir = find_step_dir(Path(path))
    return Checkpoint(step_dir, read_metadata(step_dir))


def saved_steps(folder: Path) -> list[int]:
    """The steps saved in a manager's folder, ascending (none when it does not exist)."""
    if not folder.is_dir():
        return []
    return sorted(int(p.name) for p in folder.iterdir() if p.name.isdigit() and p.is_dir())


def find_step_dir(path: str | Path, shipped: Path | None = None) -> Path:
    """A step directory from a run's log directory (its best checkpoint, else its latest), a
    checkpoints folder (its latest step), a step directory itself, or the name of a shipped checkpoint
    (`rllock pretrained`) where no such path exists."""
    path = Path(path)
    shipped = SHIPPED if shipped is None else shipped
    if not path.exists() and SHIPPED_NAME.match(str(path)) and str(path) in shipped_names(shipped):
        path = shipped / str(path)
    if not path.is_dir():
        names = ", ".join(shipped_names(shipped)) or "none"
        raise RLLockError(f"no such checkpoint directory or shipped checkpoint: {path} (shipped: {names})")
    if (path / "meta").is_dir() and (path / "state").is_dir():
        return path
    for folder in (path / "best", path / "checkpoints", path):
        steps = saved_steps(folder)
        if steps:
            return folder / str(steps[-1])
    raise RLLockError(
        f"{path} holds no RL-Lock checkpoint (expected best/, checkpoints/ or a step directory)"
    )


def read_metadata(step_dir: Path) -> Metadata:
    try:
        doc = json.loads((step_dir / "meta" / "metadata").read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RLLockError(f"checkpoint {step_dir} is corrupted or unreadable: {exc}") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise RLLockError(f"{step_dir} is not an RL-Lock checkpoint")
    try:
        return Metadata.from_json(doc)
    except (KeyError, TypeError, ValueError) as exc:
        problem = f"{type(exc).__name__}: {exc}"
        raise RLLockError(f"checkpoint {step_dir} has damaged metadata ({problem})") from None


def write_metadata(step_dir: Path, metadata: Metadata) -> None:
    """The metadata document of a step directory that orbax did not write (a shipped checkpoint's)."""
    (step_dir / "meta").mkdir(parents=True, exist_ok=True)
    (step_dir / "meta" / "metadata").write_text(json.dumps(metadata.to_json()))


def newest_readable(logdir: Path, read: Callable[[Path], T]) -> T:
    """`read` of the newest checkpoint of the run in `logdir` that it can read (an unreadable one is
    skipped with a warning)."""
    if not logdir.exists():
        raise RLLockError(
            f"cannot resume {logdir}: no such run directory (give the --logdir of a training run)"
        )
    if not logdir.is_dir():
        raise RLLockError(f"cannot resume {logdir}: it is a file, not a run directory")
    for step in saved_steps(logdir / "checkpoints")[::-1]:
        try:
            return read(logdir / "checkpoints" / str(step))
        except RLLockError as exc:
            log.warning("%s; falling back to the checkpoint before it", exc)
    raise RLLockError(
        f"cannot resume {logdir}: it holds no readable checkpoint (start it again without --resume)"
    )


def run_config(logdir: Path, *, minutes: float, max_learner_steps: int | None = None) -> TrainConfig:
    """The config of the training run in `logdir`, read from its newest readable checkpoint, with
    `minutes` more to train (and a new step limit, when given)."""
    config = newest_readable(logdir, read_metadata).config
    limit = max_learner_steps if max_learner_steps is not None else config.max_learner_steps
    return dataclasses.replace(config, logdir=str(logdir), minutes=minutes, max_learner_steps=limit)
