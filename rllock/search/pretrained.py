"""Trained checkpoints shipped inside the package, by name: `cube4-k9`, `sofa-k19`, ...

A shipped checkpoint is a step directory like a training run's, under `rllock/checkpoints/<name>/`:
`state/` holds the network parameters only (no optimizer state, no replay buffer) and `meta/metadata`
the run's metadata (task, config, validation, counters, and the command, commit, machine and date of
each training session) plus a `shipped` record. Wherever a checkpoint path is taken (`generate`,
`bench learning`, `rllock.load_policy`), a name resolves to its shipped directory when no such path
exists. Shipped files name no absolute path of the machine that made them (`portable`).
"""

from __future__ import annotations

import dataclasses
import datetime
import re
import shutil
from pathlib import Path

from rllock.errors import RLLockError
from rllock.files import checkpoint as ckpt
from rllock.files import orbax_io
from rllock.files.provenance import portable, portable_sessions
from rllock.search.inference import load_network


def describe(name: str, folder: Path | None = None) -> dict:
    """One line of `rllock pretrained`: task, settings, training, validation and provenance."""
    meta = ckpt.read_metadata((ckpt.SHIPPED if folder is None else folder) / name)
    task, validation, sessions = meta.task, meta.validation or {}, list(meta.sessions)
    return {
        "name": name,
        "task": f"tasks {task['tasks']}" if meta.multitask else f"{task['shape']} K={task['pieces']}",
        "canvas": meta.canvas,
        "simulations": meta.config.mcts.simulations,
        "training_minutes": round(meta.counters.get("seconds", 0.0) / 60, 1),
        "init": meta.config.init,  # the checkpoint it was fine-tuned from; its training is not counted
        "learner_steps": meta.step,
        "validation_success": validation.get("success_rate"),
        "validation_episodes": validation.get("episodes"),
        "commit": sessions[0]["commit"] if sessions else None,
        "machine": sessions[0]["machine"] if sessions else None,
        "sessions": sessions,
    }


def machine_summary(machine: str | None) -> str:
    """The training machine in a table cell: '16 x Intel Xeon, gpu (NVIDIA H100 80GB HBM3)' gives
    '16 cores, NVIDIA H100 80GB HBM3'; training minutes mean little without it."""
    match = re.fullmatch(r"(\d+) x .*, (\w+) \((.*)\)", machine or "")
    if match is None:
        return machine or "-"
    cores, platform, kind = match.groups()
    return f"{cores} cores" if platform == "cpu" else f"{cores} cores, {kind}"


# orbax's marker of a finished save in `state/`: it checks that the file exists, not what it says.
COMMIT_SUCCESS = "commit_success.txt"


def commit_line(state: str) -> str:
    """orbax's words in `commit_success.txt`, for the `state/` folder at the portable path `state`."""
    return f"Checkpoint commit was successful to {state}"


def portable_meta(meta: ckpt.Metadata) -> ckpt.Metadata:
    """`meta` with the absolute paths that training writes into it made `portable`: the config's
    `logdir` and `init` and those in each session's command line. Nothing else changes."""
    config = meta.config
    init = None if config.init is None else portable(config.init)
    sessions = tuple(portable_sessions(meta.sessions))
    return dataclasses.replace(
        meta,
        config=dataclasses.replace(config, logdir=portable(config.logdir), init=init),
        sessions=sessions,
    )


def ship(source: Path, name: str, *, into: Path | None = None) -> Path:
    """Copy the best checkpoint of the run in `source` (or the step directory `source`) into `into`
    as `name`: parameters and metadata only. Replaces an earlier checkpoint of that name.

    The copy names no absolute path (`portable`): `shipped.from` is the step directory relative to
    the current directory when under it, else from the run's folder down (`cube4-k9/best/5703`); so
    are the config's `logdir` and `init` and the paths in the sessions' command lines; and orbax's
    `state/commit_success.txt` (only its existence matters to orbax) names `state/` the same way:
    `rllock/checkpoints/<name>/state` for the package's own checkpoints, `<name>/state` where
    neither the current directory nor the package's folder holds it."""
    if not ckpt.SHIPPED_NAME.match(name):
        raise RLLockError(f"bad checkpoint name {name!r}: use lower-case words like cube4-k9 or sofa-k19")
    step_dir = ckpt.find_step_dir(source)
    meta = portable_meta(ckpt.read_metadata(step_dir))
    _, _, params = load_network(step_dir)
    shipped = {
        "name": name,
        "from": portable(step_dir),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }
    meta = dataclasses.replace(meta, shipped=shipped)
    into = ckpt.SHIPPED if into is None else into
    into.mkdir(parents=True, exist_ok=True)
    staging = into / f".{name}.partial"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    orbax_io.write_state(staging / "state", {"params": params})
    ckpt.write_metadata(staging, meta)
    target = into / name
    # orbax wrote the absolute staging path in it; the file must stay, its words are for people.
    (staging / "state" / COMMIT_SUCCESS).write_text(commit_line(portable((target / "state").absolute(), 2)))
    shutil.rmtree(target, ignore_errors=True)
    staging.rename(target)
    return target
