"""Shipped files name no absolute path of the machine that made them: the packaged checkpoints, the
docs, the README, the kept replay snapshots' records, and what `rllock pretrained --ship` writes."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

from helpers import save_run

from rllock.files import checkpoint as ckpt
from rllock.files.provenance import portable
from rllock.search import pretrained
from rllock.search.inference import load_policy
from rllock.search.mcts import MCTSConfig
from rllock.search.network import NetConfig

ROOT = Path(__file__).resolve().parents[1]
# A machine's absolute path: a top-level folder of a home, workspace or scratch area, where no word,
# dot, `~` or `-` comes right before the slash (so `https://x.org/home/`, `a/tmp/b`, `./tmp/` and
# `~/work/` are not), or a Windows user folder.
MACHINE_PATH = re.compile(
    rb"(?<![\w.~-])/(?:work|root|home|tmp|Users|mnt|var|opt|private|scratch|srv|data)/"
    rb"|\b[A-Za-z]:\\+Users\\"
)
NET = NetConfig(canvas=4, features=(4, 8))
MCTS = MCTSConfig(simulations=8, max_considered=4, raw_samples=256, candidates=8)


def shipped_files() -> list[Path]:
    files = [ROOT / "README.md"]
    for folder in (ROOT / "rllock" / "checkpoints", ROOT / "docs"):
        files += sorted(p for p in folder.rglob("*") if p.is_file())
    # Kept replay snapshots' records (`scripts/keep_replay.py`); the arrays beside them are numbers.
    return files + sorted((ROOT / "data").rglob("*.json")) + sorted((ROOT / "data").rglob("*.md"))


def machine_paths(data: bytes) -> list[str]:
    """Each machine path in `data`, with 30 bytes either side."""
    hits = MACHINE_PATH.finditer(data)
    return [data[max(m.start() - 30, 0) : m.end() + 30].decode("latin-1") for m in hits]


def test_the_pattern_finds_machine_paths_and_nothing_else():
    found = [
        b'"logdir": "/work/runs/cube4-k8"',
        b"--logdir /tmp/cube6-k22 --simulations",
        b"successful to /home/me/rllock/checkpoints/.x.partial/state",
        b"(`/Users/me/runs`)",
        b"C:\\Users\\me\\runs",
    ]
    not_found = [
        b'"logdir": "runs/cube4-k8"',
        b"see https://example.org/home/index.html or file:///work",
        b"(K-1-i)/K, validation/<group>/success_rate, a/tmp/b, ./tmp/x, ~/work/x",
    ]
    assert all(MACHINE_PATH.search(text) for text in found)
    assert not any(MACHINE_PATH.search(text) for text in not_found)


def test_shipped_checkpoints_docs_and_readme_name_no_machine_path():
    files = shipped_files()
    assert len(ckpt.shipped_names()) >= 1 and any(p.name == "results.md" for p in files)
    bad = {str(p.relative_to(ROOT)): hits for p in files if (hits := machine_paths(p.read_bytes()))}
    assert bad == {}


def test_every_shipped_checkpoint_keeps_its_commit_marker():
    for name in ckpt.shipped_names():
        state = ckpt.SHIPPED / name / "state"
        assert (state / pretrained.COMMIT_SUCCESS).read_text() == pretrained.commit_line(
            f"rllock/checkpoints/{name}/state"
        ), name


def test_ship_writes_no_absolute_path(tmp_path, monkeypatch):
    run = tmp_path / "run"
    argv = [f"{tmp_path}/venv/bin/rllock", "train", "--logdir", str(run), f"--init={tmp_path}/general"]
    monkeypatch.setattr(sys, "argv", argv)  # the command line provenance records
    save_run(run, "box:4x4x2", 4, net=NET, mcts=MCTS, init=str(tmp_path / "general"))
    step_meta = run / "best" / "7" / "meta" / "metadata"
    meta = json.loads(step_meta.read_text())
    meta["config"]["logdir"] = str(run)  # as `rllock train --logdir /abs/run` writes it
    step_meta.write_text(json.dumps(meta))
    assert machine_paths(step_meta.read_bytes()) or str(tmp_path) in step_meta.read_text()

    for cwd in (ROOT, tmp_path):  # the run outside, then under, the current directory
        monkeypatch.chdir(cwd)
        target = pretrained.ship(run, "box-k4", into=tmp_path / "shipped")
        for path in (target / "meta" / "metadata", target / "state" / pretrained.COMMIT_SUCCESS):
            text = path.read_text()
            assert str(tmp_path) not in text and not machine_paths(path.read_bytes()), (cwd, path, text)
        shipped = json.loads((target / "meta" / "metadata").read_text())
        assert shipped["shipped"]["from"] == "run/best/7"
        assert shipped["config"]["logdir"] == "run" and shipped["config"]["init"] == "general"
        assert shipped["sessions"][0]["command"] == "rllock train --logdir run --init=general"
        assert {k: v for k, v in shipped.items() if k not in ("config", "sessions", "shipped")} == {
            k: v for k, v in meta.items() if k not in ("config", "sessions")
        }
        assert (target / "state" / pretrained.COMMIT_SUCCESS).read_text() == pretrained.commit_line(
            "box-k4/state" if cwd == ROOT else "shipped/box-k4/state"
        )
        assert load_policy(str(target)).step == 7  # orbax still restores it


def test_portable_paths():
    assert portable("runs/cube4-k8/best/3901") == "runs/cube4-k8/best/3901"
    assert portable(Path.cwd() / "runs" / "x" / "best" / "5") == "runs/x/best/5"
    assert portable("/nowhere/runs/cube4-k9/best/5703") == "cube4-k9/best/5703"
    assert portable("/nowhere/runs/cube4-k9/checkpoints/5703") == "cube4-k9/checkpoints/5703"
    assert portable("/nowhere/cube6-k22") == "cube6-k22"
    assert portable("/nowhere/x/general/state", 2) == "general/state"
    assert portable(ckpt.SHIPPED / "general") == "rllock/checkpoints/general"
