"""Orbax checkpoints of the learner, and what they remember about their task.

A training run's log directory holds `checkpoints/<step>/` (the latest few) and `best/<step>/` (the
checkpoint with the best validation success rate). Each step directory has `state/` (params, optimizer
state, step, PRNG key: an orbax StandardSave, restored device-independently against an abstract tree
built on this host) and `meta/metadata` (JSON): the task identity, the run's whole config (the one
document that both `--resume` and `generate` read), the validation score and the run's counters. That
document is read and written only here, as a typed `Metadata`; `open_checkpoint` finds a step directory
and reads it once.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import datetime
import json
import logging
import os
import platform
import re
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax
import numpy as np
import orbax.checkpoint as ocp

from rllock.config import TrainConfig, from_flat, from_json, to_json
from rllock.core.env import Task, make_task
from rllock.core.shapes import from_xfastest, grid_sha256, to_xfastest
from rllock.core.verifier import CHECKER_VERSION
from rllock.errors import RLLockError

FORMAT = "rllock-checkpoint"
META_VERSION = 2
# Trained checkpoints shipped inside the package (see rllock.search.pretrained), reached by name.
SHIPPED = Path(__file__).resolve().parents[1] / "checkpoints"
SHIPPED_NAME = re.compile(r"^[a-z][a-z0-9]*(-k[0-9]+)?$")
# An absolute path inside a command line: at its start, after a space or after `--flag=`.
_ABSOLUTE_IN_COMMAND = re.compile(r"(?<![^\s=])/[^\s]*")
# The folder that holds the `rllock` package: the repository, or site-packages.
_PACKAGE_ROOT = Path(__file__).resolve().parents[2]


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


def run_config(logdir: Path, *, minutes: float, max_learner_steps: int | None = None) -> TrainConfig:
    """The config of the training run in `logdir`, read from its newest readable checkpoint, with
    `minutes` more to train (and a new step limit, when given)."""
    if not logdir.exists():
        raise RLLockError(
            f"cannot resume {logdir}: no such run directory (give the --logdir of a training run)"
        )
    if not logdir.is_dir():
        raise RLLockError(f"cannot resume {logdir}: it is a file, not a run directory")
    for step in saved_steps(logdir / "checkpoints")[::-1]:
        try:
            config = read_metadata(logdir / "checkpoints" / str(step)).config
        except RLLockError:
            continue
        limit = max_learner_steps if max_learner_steps is not None else config.max_learner_steps
        return dataclasses.replace(config, logdir=str(logdir), minutes=minutes, max_learner_steps=limit)
    raise RLLockError(
        f"cannot resume {logdir}: it holds no readable checkpoint (start it again without --resume)"
    )


def _commit() -> str | None:
    """The git commit of this source tree (with "-dirty" when it has changes), or None outside git."""
    root = Path(__file__).resolve().parents[2]
    # close_fds=False lets subprocess use posix_spawn: no fork in a process where JAX runs threads.
    try:
        head = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            timeout=10,
            close_fds=False,
        )
        dirty = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=10,
            close_fds=False,
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    if head.returncode != 0:
        return None
    return head.stdout.strip() + ("-dirty" if dirty.stdout.strip() else "")


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def portable(path: str | Path, tail: int | None = None) -> str:
    """`path` as a shipped file records it, naming nothing of the machine that wrote it. A relative
    path stays as it is. An absolute one becomes relative to the current directory when it lies
    under it (`runs/cube4-k9/best/5703` from the directory that holds `runs/`); else relative to the
    folder that holds the `rllock` package when under that (`rllock/checkpoints/cube4-k9`); else its
    last `tail` parts, by default the run's folder and the rest below it: from the folder above
    `best/` or `checkpoints/` (`/data/runs/cube4-k9/best/5703` gives `cube4-k9/best/5703`), or the
    last part alone where there is no such folder (a run's log directory, `/tmp/cube6-k22` gives
    `cube6-k22`)."""
    path = Path(path)
    if not path.is_absolute():
        return str(path)
    for candidate in (path, path.resolve()):
        for base in (Path.cwd(), Path.cwd().resolve(), _PACKAGE_ROOT):
            if candidate.is_relative_to(base) and base != Path(base.anchor):
                return str(candidate.relative_to(base))
    parts = path.parts[1:]
    if tail is None:
        tail = 1
        for i in range(len(parts) - 1, 0, -1):
            if parts[i] in ("best", "checkpoints"):
                tail = len(parts) - i + 1
                break
    return str(Path(*parts[-tail:])) if parts else "."


def portable_command(command: str) -> str:
    """A command line with every absolute path in it made `portable`."""
    return _ABSOLUTE_IN_COMMAND.sub(lambda m: portable(m.group()), command)


def provenance() -> dict:
    """What made a checkpoint, for the record: command, commit, machine and date."""
    device = jax.devices()[0]
    return {
        "command": portable_command(" ".join(["rllock", *sys.argv[1:]])),
        "commit": _commit(),
        "machine": f"{os.cpu_count()} x {_cpu_model()}, {device.platform} ({device.device_kind})",
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }


def task_identity(task: Task, canvas: int) -> dict:
    """What a checkpoint is for: loading it for anything else is an error."""
    grid = task.topology.grid
    return {
        "shape": task.shape_name,
        "dimensions": list(grid.shape),
        "grid": [int(v) for v in to_xfastest(grid.astype(np.int8))],
        "grid_sha256": grid_sha256(grid),
        "pieces": task.pieces,
        "removal": task.removal,
        "canvas": canvas,
        "checker_version": CHECKER_VERSION,
    }


def task_from_identity(identity: dict) -> Task:
    grid = from_xfastest(np.asarray(identity["grid"]), tuple(identity["dimensions"])) != 0
    return make_task(grid, int(identity["pieces"]), identity["removal"], name=identity["shape"])


def describe_identity(identity: dict) -> str:
    """A task identity (`task_identity`, or a multi-task run's) in words."""
    if "tasks" in identity:
        return f"tasks {identity['tasks']}, removal {identity.get('removal')}"
    dims = "x".join(str(d) for d in identity["dimensions"])
    return f"{identity['shape']} ({dims}) K={identity['pieces']}, removal {identity['removal']}"


def check_same_task(saved: dict, wanted: dict, where: Path) -> None:
    """Refuse a checkpoint made for another task than `wanted`, saying both in words."""
    keys = ("tasks", "grid_sha256", "pieces", "removal", "canvas", "checker_version")
    differs = [key for key in keys if saved.get(key) != wanted.get(key)]
    if not differs:
        return
    there, here = describe_identity(saved), describe_identity(wanted)
    if "canvas" in differs:
        there, here = (
            f"{there}, on a {saved.get('canvas')}^3 canvas",
            f"{here}, on a {wanted.get('canvas')}^3 canvas",
        )
    if "checker_version" in differs:
        there = f"{there}, checkers version {saved.get('checker_version')}"
        here = f"{here}, checkers version {wanted.get('checker_version')}"
    if there == here:  # only the grid differs: two shapes of the same name and size
        here = f"{here}, but another shape of that name and size"
    raise RLLockError(f"checkpoint {where} was made for another task: {there}; this task is {here}")


def manager(directory: Path, keep: int) -> ocp.CheckpointManager:
    return ocp.CheckpointManager(
        directory.absolute(),
        options=ocp.CheckpointManagerOptions(max_to_keep=keep, create=True),
        item_names=("state", "meta"),
    )


def save(mngr: ocp.CheckpointManager, step: int, state: Any, metadata: Metadata) -> None:
    """Save (replacing an earlier save of the same step, whose metadata may be stale) and wait."""
    if step in mngr.all_steps():
        mngr.delete(step)
    mngr.save(
        step,
        args=ocp.args.Composite(
            state=ocp.args.StandardSave(state), meta=ocp.args.JsonSave(metadata.to_json())
        ),
        force=True,
    )
    mngr.wait_until_finished()


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


# How long a failed restore waits for its other reads to end before it cancels them.
_DRAIN_SECONDS = 30.0


class _DrainingLoop(asyncio.SelectorEventLoop):
    """An event loop that, when closed with tasks still running, first lets them end.

    Orbax runs a restore in a fresh loop and closes it as soon as one read fails, while TensorStore
    goes on with the others: their completions then land on a closed loop ("RuntimeError: Event loop
    is closed", printed from TensorStore's threads) and their coroutines, collected unfinished, print a
    traceback each with a TensorStore spec dump. A damaged checkpoint would bury the one error line
    under hundreds of lines; letting the reads end while the loop is open leaves nothing to print."""

    def close(self) -> None:
        if not self.is_closed() and not self.is_running():
            pending = asyncio.all_tasks(self)
            if pending:
                _, late = self.run_until_complete(asyncio.wait(pending, timeout=_DRAIN_SECONDS))
                for task in late:
                    task.cancel()
                if late:
                    self.run_until_complete(asyncio.wait(late, timeout=_DRAIN_SECONDS))
                for task in pending:
                    # Retrieved, so asyncio does not log each one as "never retrieved" when it is freed.
                    if task.done() and not task.cancelled():
                        task.exception()
        super().close()


class _DrainingPolicy(asyncio.DefaultEventLoopPolicy):
    def new_event_loop(self) -> asyncio.AbstractEventLoop:
        return _DrainingLoop()


@contextlib.contextmanager
def _quiet_restore() -> Iterator[None]:
    """Orbax's loops drain before they close (`_DrainingLoop`), and its warnings about what it cannot
    read stay unprinted: a restore either succeeds or raises, and the caller reports the error once."""
    loggers = [logging.getLogger(name) for name in ("absl", "orbax")]
    levels = [logger.level for logger in loggers]
    policy = asyncio.get_event_loop_policy()
    asyncio.set_event_loop_policy(_DrainingPolicy())
    for logger in loggers:
        logger.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        asyncio.set_event_loop_policy(policy)
        for logger, level in zip(loggers, levels, strict=True):
            logger.setLevel(level)


# What TensorStore adds to its own words: the spec it was opening, each driver it went through, and the
# database's folder, which the message names already.
_TENSORSTORE_NOISE = (
    re.compile(r" \[tensorstore_spec.*$"),
    re.compile(r'Error opening "\w+" driver: '),
    re.compile(r' in OCDBT database at local file "[^"]*"'),
)


def _root_cause(exc: BaseException, step_dir: Path) -> str:
    """The innermost error behind `exc`, in short: orbax wraps TensorStore's own words (such as
    "DATA_LOSS: Error reading ...") in a message that dumps the whole TensorStore spec."""
    seen: set[int] = set()
    while id(exc) not in seen:
        seen.add(id(exc))
        inner = exc.__cause__ or exc.__context__
        if inner is None:
            break
        exc = inner
    text = str(exc).strip()
    text = text.splitlines()[0] if text else type(exc).__name__
    for noise in _TENSORSTORE_NOISE:
        text = noise.sub("", text)
    text = text.replace(f"{step_dir.absolute()}/", "")
    return text if len(text) <= 300 else text[:297] + "..."


def restore_like(step_dir: Path, template: Any, *, partial: bool = False) -> Any:
    """The state saved in `step_dir`, with the structure, shapes and dtypes of `template` (arrays or
    `jax.eval_shape` structs), placed on this host's default device (so a GPU-trained checkpoint loads on
    a CPU-only machine). With `partial`, `template` may name a subtree of what was saved, such as
    {"params": ...}: only that is read."""
    device = jax.sharding.SingleDeviceSharding(jax.devices()[0])
    abstract = jax.tree_util.tree_map(
        lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=device), template
    )
    path = (step_dir / "state").absolute()
    try:
        with _quiet_restore():
            if partial:
                args = ocp.args.PyTreeRestore(
                    item=abstract,
                    partial_restore=True,
                    restore_args=ocp.checkpoint_utils.construct_restore_args(abstract),
                )
                with contextlib.closing(ocp.PyTreeCheckpointer()) as checkpointer:
                    return checkpointer.restore(path, args=args)
            with contextlib.closing(ocp.StandardCheckpointer()) as standard:
                return standard.restore(path, abstract)
    except Exception as exc:  # orbax raises many kinds of errors for damaged files
        raise RLLockError(
            f"checkpoint {step_dir} is corrupted or unreadable: {_root_cause(exc, step_dir)}"
        ) from None
