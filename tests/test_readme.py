"""The README's commands that need no training run as written, in order, in a fresh folder: they must
not drift from the command line."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# The commands a reader can run in a minute without a trained run of their own; synopsis lines (with
# [optional] parts) and the mesh example (it needs the reader's model.stl) are left out.
RUNNABLE = re.compile(r"^rllock (solve|verify|show|export|pretrained)\b")


def readme_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    commands = []
    for block in re.findall(r"```bash\n(.*?)```", text, flags=re.S):
        for line in block.splitlines():
            command = line.split("  #")[0].strip()
            if RUNNABLE.match(command) and "[" not in command and "model.stl" not in command:
                commands.append(command)
    return commands


def test_the_readme_lists_the_commands_this_test_runs():
    commands = readme_commands()
    assert commands[0] == "rllock solve --shape cube4 --pieces 7 --seed 0 --out out/cube4"
    assert sum(c.startswith("rllock show") for c in commands) == 2
    assert sum(c.startswith("rllock export") for c in commands) == 2


@pytest.mark.slow
def test_the_readme_commands_run_as_written_in_order(tmp_path):
    (tmp_path / "rllock").symlink_to(ROOT / "rllock")  # the README's paths are from the repository root
    for command in readme_commands():
        args = shlex.split(command)[1:]
        proc = subprocess.run(
            [sys.executable, "-m", "rllock.orchestration.cli", *args],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert proc.returncode == 0, (command, proc.stdout, proc.stderr)
        assert "Traceback" not in proc.stderr, (command, proc.stderr)
    assert (tmp_path / "cube4.png").stat().st_size > 1000
    assert sorted(p.name for p in (tmp_path / "burr").iterdir())[0].endswith(".xmpuzzle")
    assert len(list((tmp_path / "prints").glob("piece_*.stl"))) == 7
