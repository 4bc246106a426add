"""Replay snapshots of guide runs, kept and pooled: what `rllock train-guide --replay-from` learns from.

Searches are what a guide run spends its time on; the learner's steps are cheap. So a guide can be taught
again, without searching, on every state of one or more runs' snapshots at once (`load_pool`: the
learner alone, in one process, `rllock.orchestration.builder.OfflineGuideBuilder`), and a run's snapshot can
be kept apart from its run (`keep_snapshot`) with a record of what made it. Each checkpoint of such a training
records the snapshots it learned from (path, states, SHA-256, the sessions that made them), so that a shipped
guide names its data and a resume can check it goes on on the same states.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from rllock.config import GuideTrainConfig
from rllock.errors import RLLockError
from rllock.files import checkpoint as ckpt
from rllock.files.provenance import portable, portable_sessions
from rllock.learner.guide_learner import GuideBuffer, pool, read_snapshot, write_snapshot
from rllock.search.guide import channels
from rllock.search.guide_checkpoint import read_guide_metadata


def snapshot_paths(replay_from: str) -> list[Path]:
    """The snapshot files `--replay-from` names: a run folder stands for its `replay.npz`."""
    paths = []
    for source in filter(None, (s.strip() for s in replay_from.split(","))):
        path = Path(source)
        path = path / "replay.npz" if path.is_dir() else path
        if not path.is_file():
            raise RLLockError(f"--replay-from {source}: no replay snapshot there (a train-guide run or .npz)")
        paths.append(path)
    if not paths:
        raise RLLockError("--replay-from names no snapshot")
    return paths


def sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def made_by(path: Path) -> list[dict]:
    """The sessions of the run that made the snapshot at `path` (command, commit, machine, date): its
    run's checkpoint metadata, or for a kept snapshot (`keep_snapshot`) the record beside it."""
    record = path.with_suffix(".json")
    try:
        if path.name == "replay.npz" and ckpt.saved_steps(path.parent / "checkpoints"):
            return list(read_guide_metadata(ckpt.find_step_dir(path.parent)).get("sessions", []))
        if record.is_file():
            return list(json.loads(record.read_text()).get("sessions", []))
    except (OSError, json.JSONDecodeError, RLLockError) as exc:
        raise RLLockError(f"the record of replay snapshot {path} is unreadable: {exc}") from None
    return []


def load_pool(config: GuideTrainConfig) -> tuple[GuideBuffer, list[dict]]:
    """The pooled buffer of `config.replay_from` and a record of each snapshot in it: its path, states,
    SHA-256 and the sessions that made it."""
    paths = snapshot_paths(config.replay_from)
    snapshots = {str(p): read_snapshot(p) for p in paths}
    buffer = pool(snapshots, config.guide.window, channels(config.guide))
    record = [
        {
            "source": str(p),
            "states": len(snapshots[str(p)]["target"]),
            "sha256": sha256(p),
            "made_by": made_by(p),
        }
        for p in paths
    ]
    return buffer, record


def keep_snapshot(run: Path, out: Path) -> dict:
    """Keep the replay snapshot of the guide run in `run` at `out` (a compressed .npz) with the run's
    config, counters and sessions beside it (`out` with .json), made portable: the searches a guide
    learns from outlive the machine that made them (`--replay-from OUT`)."""
    doc = read_guide_metadata(ckpt.find_step_dir(run))
    snapshot = read_snapshot(run / "replay.npz")
    size = len(snapshot["target"])
    out.parent.mkdir(parents=True, exist_ok=True)
    write_snapshot(out, snapshot, compressed=True)
    record = {
        "run": portable(run),
        "states": size,
        "sha256": sha256(out),
        "config": doc["config"] | {"logdir": portable(doc["config"]["logdir"])},
        "counters": doc.get("counters", {}),
        "sessions": portable_sessions(doc.get("sessions", [])),
    }
    out.with_suffix(".json").write_text(json.dumps(record, indent=1) + "\n")
    return record
