"""Guide network checkpoints (`rllock train-guide`) and loading one for `rllock solve --guide`.

A guide run's log directory holds `checkpoints/<step>/` like a training run's: `state/` (orbax: the
parameters, optimizer state, step and PRNG key) and `meta/metadata`, a JSON document of format
`rllock-guide` with the run's config, its counters and the sessions that trained it. A shipped guide
(`rllock/checkpoints/guide`) keeps the parameters only. Any other checkpoint, a missing one or a damaged
one is a one-line error before any search.
"""

from __future__ import annotations

import json
from pathlib import Path

import jax

from rllock.config import GuideTrainConfig, from_json, to_json
from rllock.errors import RLLockError
from rllock.files import checkpoint as ckpt
from rllock.files.orbax_io import restore_like
from rllock.search.guide import Guide, init_guide

FORMAT = "rllock-guide"
VERSION = 1
SHIPPED_GUIDE = "guide"  # what `--guide` alone loads


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
    step_dir = ckpt.find_step_dir(source)
    doc = read_guide_metadata(step_dir)
    try:
        config = from_json(GuideTrainConfig, doc["config"]).guide
    except (KeyError, TypeError, ValueError) as exc:
        raise RLLockError(f"guide checkpoint {step_dir} has damaged metadata ({exc})") from None
    template = {"params": jax.eval_shape(lambda key: init_guide(config, key), jax.random.PRNGKey(0))}
    params = restore_like(step_dir, template, partial=True)["params"]
    return Guide(config, params, str(step_dir))
