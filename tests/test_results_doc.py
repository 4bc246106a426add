"""docs/results.md and the README stay short, and every `rllock` command they give parses with today's
command line: a flag renamed or removed fails here, not in a reader's terminal."""

from __future__ import annotations

import contextlib
import io
import re
import shlex
from functools import cache
from pathlib import Path

from rllock.orchestration.cli.main import build_parser

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs" / "results.md"
README = ROOT / "README.md"
# Synopsis lines and placeholders are not commands to parse.
PLACEHOLDER = re.compile(r"\[|<|\.\.\.")


def results_commands() -> list[str]:
    """Every `rllock ...` in backticks in docs/results.md."""
    return re.findall(r"`(rllock [^`]*)`", RESULTS.read_text())


def readme_commands() -> list[str]:
    """Every line of the README's ```bash blocks that runs `rllock`, continuation lines joined and the
    trailing comment dropped."""
    commands = []
    for block in re.findall(r"```bash\n(.*?)```", README.read_text(), flags=re.S):
        for line in block.replace("\\\n", " ").splitlines():
            command = line.split("  #")[0].strip()
            if command.startswith("rllock "):
                commands.append(command)
    return commands


def parse_error(command: str) -> str | None:
    """None if `command` parses with the real parser, else what argparse said."""
    stderr = io.StringIO()
    try:
        with contextlib.redirect_stderr(stderr), contextlib.redirect_stdout(io.StringIO()):
            parser().parse_args(shlex.split(command)[1:])
    except SystemExit as exit:
        return f"exit {exit.code}: {stderr.getvalue().strip()}"
    return None


@cache
def parser():
    return build_parser()


COMMANDS = [("results.md", c) for c in results_commands()] + [("README.md", c) for c in readme_commands()]


def test_the_docs_give_commands_to_check():
    assert sum(doc == "results.md" for doc, _ in COMMANDS) >= 50
    assert sum(doc == "README.md" for doc, _ in COMMANDS) >= 10


def test_every_command_parses():
    """Placeholders ([optional], <name>, ...) are left out."""
    failures = [
        f"{doc}: `{command}` does not parse ({error})"
        for doc, command in COMMANDS
        if not PLACEHOLDER.search(command) and (error := parse_error(command)) is not None
    ]
    assert failures == []


def test_a_bad_flag_fails_the_check():
    assert parse_error("rllock solve --shape cube4 --pieces 7 --no-such-flag") is not None
    assert parse_error("rllock bench frobnicate") is not None
    assert parse_error("rllock solve --shape cube4 --pieces 7 --out out/x") is None


def test_results_and_readme_stay_short():
    assert len(RESULTS.read_text().splitlines()) <= 400
    assert len(README.read_text().splitlines()) <= 200
