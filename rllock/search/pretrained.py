"""Trained checkpoints shipped inside the package, by name: `cube4-k9`, `sofa-k19`, ...

A shipped checkpoint is a step directory like a training run's, under `rllock/checkpoints/<name>/`:
`state/` holds the network parameters only (no optimizer state, no replay buffer) and `meta/metadata`
the run's metadata (task, config, validation, counters, and the command, commit, machine and date of
each training session) plus a `shipped` record. Wherever a checkpoint path is taken (`generate`,
`bench learning`, `rllock.load_policy`), a name resolves to its shipped directory when no such path
exists.
"""

from __future__ import annotations

import datetime
import json
import re
import shutil
from pathlib import Path

import jax
import orbax.checkpoint as ocp

from rllock.config import NetConfig, from_json
from rllock.errors import RLLockError
from rllock.files import checkpoint as ckpt
from rllock.search.network import init_params


def describe(name: str, folder: Path | None = None) -> dict:
    """One line of `rllock pretrained`: task, settings, training, validation and provenance."""
    meta = ckpt.read_meta((ckpt.SHIPPED if folder is None else folder) / name)
    task, config, counters = meta["task"], meta["config"], meta.get("counters", {})
    validation = meta.get("validation") or {}
    sessions = meta.get("sessions", [])
    return {
        "name": name,
        "task": f"tasks {task['tasks']}" if "tasks" in task else f"{task['shape']} K={task['pieces']}",
        "canvas": task["canvas"],
        "simulations": config["mcts"]["simulations"],
        "training_minutes": round(counters.get("seconds", 0.0) / 60, 1),
        "init": config.get("init"),  # the checkpoint it was fine-tuned from; its training is not counted
        "learner_steps": meta["step"],
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


def ship(source: Path, name: str, *, into: Path | None = None) -> Path:
    """Copy the best checkpoint of the run in `source` (or the step directory `source`) into `into`
    as `name`: parameters and metadata only. Replaces an earlier checkpoint of that name."""
    if not ckpt.SHIPPED_NAME.match(name):
        raise RLLockError(f"bad checkpoint name {name!r}: use lower-case words like cube4-k9 or sofa-k19")
    step_dir = ckpt.find_step_dir(source)
    meta = ckpt.read_meta(step_dir)
    net = from_json(NetConfig, meta["config"]["net"])
    template = {"params": jax.eval_shape(lambda key: init_params(net, key), jax.random.PRNGKey(0))}
    params = ckpt.restore_like(step_dir, template, partial=True)
    meta["shipped"] = {
        "name": name,
        "from": str(step_dir),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }
    into = ckpt.SHIPPED if into is None else into
    into.mkdir(parents=True, exist_ok=True)
    staging = into / f".{name}.partial"
    shutil.rmtree(staging, ignore_errors=True)
    (staging / "meta").mkdir(parents=True)
    saver = ocp.StandardCheckpointer()
    saver.save((staging / "state").absolute(), params)
    saver.wait_until_finished()
    (staging / "meta" / "metadata").write_text(json.dumps(meta))
    target = into / name
    shutil.rmtree(target, ignore_errors=True)
    staging.rename(target)
    return target
