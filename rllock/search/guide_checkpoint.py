"""Guide network checkpoints (`rllock train-guide`) and loading one for `rllock solve --guide`.

A guide run's log directory holds `checkpoints/<step>/` like a training run's: `state/` (orbax: the
parameters, optimizer state, step and PRNG key) and `meta/metadata`, a JSON document of format
`rllock-guide` with the run's config, its counters and the sessions that trained it (command, commit,
machine, date). A shipped guide (`rllock/checkpoints/guides/<name>`, `guide` being what `--guide` alone
loads) keeps the parameters only, and names no path of the machine that made it. Any other checkpoint, a
missing one or a damaged one is a one-line error before any search.
"""

from __future__ import annotations

import datetime
import json
import shutil
from pathlib import Path

import jax

from rllock.config import GuideTrainConfig, from_json, to_json
from rllock.errors import RLLockError
from rllock.files import checkpoint as ckpt
from rllock.files.orbax_io import restore_like, write_state
from rllock.files.provenance import portable, portable_sessions
from rllock.search.guide import Guide, init_guide
from rllock.search.pretrained import COMMIT_SUCCESS, commit_line

FORMAT = "rllock-guide"
VERSION = 1
SHIPPED_GUIDE = "guide"  # what `--guide` alone loads
GUIDES = (
    ckpt.SHIPPED / "guides"
)  # apart from the policies: `rllock pretrained` lists them in a table of their own


def guide_metadata(config: GuideTrainConfig, step: int, counters: dict, sessions: list[dict]) -> dict:
    return {
        "format": FORMAT,
        "version": VERSION,
        "step": step,
        "config": to_json(config),
        "counters": counters,
        "sessions": sessions,
    }


def read_guide_metadata(step_dir: Path) -> dict:
    try:
        doc = json.loads((step_dir / "meta" / "metadata").read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RLLockError(f"guide checkpoint {step_dir} is corrupted or unreadable: {exc}") from None
    if isinstance(doc, dict) and doc.get("format") == ckpt.FORMAT:
        raise RLLockError(
            f"{step_dir} is a policy checkpoint (rllock train), not a guide network: give --guide a run "
            "of rllock train-guide, or --guide alone for the shipped guide"
        )
    if not isinstance(doc, dict) or doc.get("format") != FORMAT or "config" not in doc:
        raise RLLockError(f"{step_dir} is not an RL-Lock guide checkpoint")
    return doc


def load_guide(source: str | Path = SHIPPED_GUIDE) -> Guide:
    """The guide network in `source`: a `rllock train-guide` run's folder (its latest checkpoint), a step
    directory, or a shipped name (`guide`)."""
    policy = not Path(source).exists() and str(source) in ckpt.shipped_names()
    step_dir = ckpt.find_step_dir(source, shipped=ckpt.SHIPPED if policy else GUIDES)
    doc = read_guide_metadata(step_dir)  # a shipped policy's name: the error says what it is
    try:
        trained = from_json(GuideTrainConfig, doc["config"])
    except (KeyError, TypeError, ValueError) as exc:
        raise RLLockError(f"guide checkpoint {step_dir} has damaged metadata ({exc})") from None
    config = trained.guide
    template = {"params": jax.eval_shape(lambda key: init_guide(config, key), jax.random.PRNGKey(0))}
    params = restore_like(step_dir, template, partial=True)["params"]
    return Guide(config, params, str(step_dir), trained.max_left)


def is_guide_run(source: Path) -> bool:
    """Whether `source` (a run folder or step directory) holds a guide network's checkpoints."""
    try:
        read_guide_metadata(ckpt.find_step_dir(source))
    except RLLockError:
        return False
    return True


def shipped_guides() -> list[str]:
    return ckpt.shipped_names(GUIDES)


def describe_guide(name: str) -> dict:
    """One line of `rllock pretrained`'s guide table: training and provenance."""
    doc = read_guide_metadata(GUIDES / name)
    sessions, counters = list(doc.get("sessions", [])), doc.get("counters", {})
    return {
        "name": name,
        "window": doc["config"]["guide"]["window"],
        "training_minutes": round(counters.get("seconds", 0.0) / 60, 1),
        "searches": counters.get("searches", 0),
        "learner_steps": doc["step"],
        "command": sessions[0].get("command") if sessions else None,
        "commit": sessions[0].get("commit") if sessions else None,
        "machine": sessions[0].get("machine") if sessions else None,
        "date": sessions[0].get("date") if sessions else None,
        "sessions": sessions,
        "replay": doc.get("replay", []),  # the snapshots it learned from, where it learned offline
    }


def ship_guide(source: Path, name: str, into: Path | None = None) -> Path:
    """Copy the latest checkpoint of the guide run in `source` into the package as `name`: the
    parameters and the metadata (paths made portable, a `shipped` record added)."""
    if not ckpt.SHIPPED_NAME.match(name):
        raise RLLockError(f"bad guide name {name!r}: use lower-case words like guide")
    step_dir = ckpt.find_step_dir(source)
    doc = read_guide_metadata(step_dir)
    guide = load_guide(step_dir)
    doc["config"]["logdir"] = portable(doc["config"]["logdir"])
    if doc["config"].get("replay_from"):
        doc["config"]["replay_from"] = ",".join(map(portable, doc["config"]["replay_from"].split(",")))
    if "replay" in doc:  # a guide trained on snapshots (train-guide --replay-from)
        doc["replay"] = [{**r, "source": portable(r["source"])} for r in doc["replay"]]
    doc["sessions"] = portable_sessions(doc.get("sessions", []))
    doc["shipped"] = {
        "name": name,
        "from": portable(step_dir),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }
    into = GUIDES if into is None else into
    staging, target = into / f".{name}.partial", into / name
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    write_state(staging / "state", {"params": guide.params})
    (staging / "meta").mkdir()
    (staging / "meta" / "metadata").write_text(json.dumps(doc))
    # orbax wrote the absolute staging path in it; the file must stay, its words are for people.
    (staging / "state" / COMMIT_SUCCESS).write_text(commit_line(portable((target / "state").absolute(), 3)))
    shutil.rmtree(target, ignore_errors=True)
    staging.rename(target)
    return target
