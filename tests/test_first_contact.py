"""What a new user meets first in `solve` and `generate`: a clean stop on Ctrl-C that keeps complete
folders, a failed search that says what it reached and what to try, and output folders checked before
any work."""

from __future__ import annotations

import math
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import run_cli

from rllock.core.env import make_task
from rllock.core.verifier import verify_labels
from rllock.files.assembly import read_assembly, write_assembly
from rllock.search.solver import solve

FILES = {"assembly.json", "assembly.puz", "assembly.png"}


def _interrupt_after(args: list[str], out: Path, folders: int, timeout: float = 240):
    """Start `rllock ARGS`, send Ctrl-C once `folders` assembly folders exist; (code, stdout, stderr)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "rllock.orchestration.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + timeout
        while len(list(out.glob("assembly_*"))) < folders:
            assert proc.poll() is None and time.monotonic() < deadline, "no assemblies came"
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        proc.kill()
    return proc.returncode, stdout, stderr


def _complete(out: Path) -> int:
    """How many assembly folders `out` holds, each checked complete and valid; no half-written one."""
    folders = sorted(out.glob("assembly_*"))
    for folder in folders:
        assert {f.name for f in folder.iterdir()} == FILES, folder
        labels, _ = read_assembly(folder)
        assert verify_labels(labels).valid
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no staging folder left
    return len(folders)


@pytest.mark.slow
def test_ctrl_c_in_solve_keeps_complete_folders_and_says_so(tmp_path):
    out = tmp_path / "out"
    args = ["solve", "--shape", "cube4", "--pieces", "7", "--count", "100000", "--time-limit", "200"]
    code, stdout, stderr = _interrupt_after([*args, "--out", str(out)], out, folders=3)
    assert code == 130 and "Traceback" not in stderr, stderr
    kept = _complete(out)
    assert kept >= 3 and f"solve: interrupted; kept {kept} valid assemblies in {out}" in stdout


@pytest.mark.slow
def test_ctrl_c_in_generate_keeps_complete_folders_and_says_so(tmp_path):
    out = tmp_path / "out"
    args = [
        "generate",
        "--checkpoint",
        "cube4-k7",
        "--count",
        "100000",
        "--batch",
        "16",
        "--time-limit",
        "200",
    ]
    code, stdout, stderr = _interrupt_after([*args, "--out", str(out)], out, folders=1)
    assert code == 130 and "Traceback" not in stderr, stderr
    kept = _complete(out)
    word = "assembly" if kept == 1 else "assemblies"
    assert kept >= 1 and f"generate: interrupted; kept {kept} valid {word} in {out}" in stdout


def test_a_failed_solve_says_what_it_reached_and_offers_a_task_that_works(tmp_path):
    out = tmp_path / "o"
    code, stdout, stderr = run_cli(
        "solve", "--shape", "desia-bunny", "--pieces", "80", "--time-limit", "6", "--out", str(out)
    )  # fmt: skip
    assert code == 1
    # stderr is a pipe, not a terminal: the search logs its progress every few seconds instead of a bar.
    lines = [line for line in stderr.splitlines() if "solve desia-bunny K=80: " in line]
    assert len(lines) >= 1 and all("nodes/s" in line and "restarts, best" in line for line in lines), stderr
    first, best, thin, works, command = stdout.strip().splitlines()
    assert first.startswith("solve: no valid assembly of desia-bunny K=80 within 6 s (")
    placed = int(best.split("best: ")[1].split(" of 79")[0])
    assert (
        0 < placed < 79 and f"chunks sampled for piece {placed + 1}" in best and "fail connectivity" in best
    )
    # The bunny's ears and feet: a tenth of it where no 3^3 block fits (tests/test_thickness.py).
    assert thin.startswith("  thin parts: 103 of the 966 voxels") and "--thicken 3" in thin, thin
    # The probe (half the time limit, at least 10 s): N = 966, K = 81 makes pieces of 11, the last
    # 966 - 80 * 11.
    assert "looking for a task near it that works, for up to 10 s" in stderr
    assert works.startswith("  a task that works: K=81, pieces of 11 and the last 86; this search (seed 0)")
    # With time enough for the same search on a busier machine (3x the probe's, and 5 s).
    found = float(works.split("found one in ")[1].split(" s")[0])
    limit = f" --time-limit {math.ceil(3 * found) + 5}" if math.ceil(3 * found) + 5 > 6 else ""
    assert command.strip() == f"rllock solve --shape desia-bunny --pieces 81{limit} --seed 0 --out {out}"
    # The offer holds: the same search finds it again.
    code, stdout, stderr = run_cli(*shlex.split(command)[1:])
    assert code == 0 and "solve: 1 valid assembly of desia-bunny K=81" in stdout, stderr
    assert verify_labels(read_assembly(out / "assembly_001")[0]).valid


def test_without_a_probe_a_failed_solve_says_what_to_try(tmp_path):
    code, stdout, _ = run_cli(
        "solve", "--shape", "desia-bunny", "--pieces", "80", "--time-limit", "1", "--probe", "0",
        "--out", str(tmp_path / "o"),
    )  # fmt: skip
    assert code == 1
    tries = stdout.strip().splitlines()[-1]
    # N = 966: K = 79 keeps pieces of 12 (the last 966 - 78 * 12), K = 81 makes them 11 (966 - 80 * 11).
    assert "K=79 (pieces of 12, the last 30) or K=81 (pieces of 11, the last 86)" in tries, tries
    assert "more time (--time-limit 2)" in tries and "--removal path" in tries


def test_a_bad_out_fails_before_any_work(tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("x")
    started = time.monotonic()
    code, _, err = run_cli("solve", "--shape", "cube4", "--pieces", "7", "--out", str(afile))
    assert code == 2 and err.strip() == f"rllock: error: --out {afile} is a file, not a folder"
    code, _, err = run_cli("solve", "--shape", "cube4", "--pieces", "7", "--out", str(afile / "sub"))
    assert code == 2 and "cannot make the folder" in err and len(err.strip().splitlines()) == 1, err
    code, _, err = run_cli("generate", "--checkpoint", "cube4-k7", "--out", str(afile / "sub"))
    assert code == 2 and "cannot make the folder" in err, err
    assert time.monotonic() - started < 60


def test_a_folder_is_written_whole_or_not_at_all(tmp_path):
    (labels,) = solve(make_task("cube4", 7), count=1, time_limit=60, seed=0)
    settings = dict(removal="straight", shape="cube4", method={"name": "search"}, seed=0, timings={})

    def broken_picture(labels: np.ndarray, verdict, folder: Path) -> None:
        (folder / "assembly.png").write_bytes(b"half")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        write_assembly(tmp_path / "assembly_001", labels, picture=broken_picture, **settings)
    assert list(tmp_path.iterdir()) == []
    write_assembly(tmp_path / "best", labels, **settings)
    (tmp_path / "best" / "stale.txt").write_text("from the previous best")
    write_assembly(tmp_path / "best", labels, **settings)  # a run's best assembly, replaced whole
    assert sorted(p.name for p in tmp_path.iterdir()) == ["best"]
    assert {p.name for p in (tmp_path / "best").iterdir()} == {"assembly.json", "assembly.puz"}


def test_the_search_reports_its_progress_while_it_runs(monkeypatch):
    from rllock.search import dfs, solver

    monkeypatch.setattr(dfs, "PROGRESS_EVERY", 0.0)
    seen: list[tuple[int, int, int]] = []
    stats = dfs.SearchStats()
    task = make_task("desia-bunny", 80)  # DESIA's count: straight removal finds none in seconds
    found = solver.search(
        task,
        seed=0,
        time_limit=2,
        stats=stats,
        report=lambda s: seen.append((s.expansions, s.restarts, s.placed)),
    )
    assert list(found) == [] and len(seen) > 10
    assert [e for e, _, _ in seen] == sorted(e for e, _, _ in seen) and seen[-1][0] <= stats.expansions
    assert [p for _, _, p in seen] == sorted(p for _, _, p in seen) and 0 < stats.placed < 79
    assert stats.deepest is not None and stats.deepest.placed == stats.placed


@pytest.mark.parametrize("command", ["solve", "generate"])
def test_help_shows_the_defaults(command):
    from rllock.orchestration.cli.main import build_parser

    sub = build_parser()._subparsers._group_actions[0].choices[command]  # type: ignore[union-attr]
    text = sub.format_help()
    for flag, default in (("--count", "1" if command == "solve" else "5"), ("--seed", "0")):
        assert f"(default {default})" in text.split(flag, 2)[-1].split("--", 1)[0], flag
    assert "a hard limit (default " in text


def test_advice_names_general_only_where_it_can_generate():
    from rllock.orchestration.cli.longwork import advice, general_serves

    fits, too_big, path = make_task("cube5", 13), make_task("box:17x2x2", 4), make_task("cube5", 13, "path")
    assert general_serves(fits) and not general_serves(too_big) and not general_serves(path)
    assert "rllock generate --checkpoint general --shape cube5 --pieces 13" in advice(
        fits, fits_general=True, more="more time"
    )
    assert "general" not in advice(path, fits_general=False, more="more time")
