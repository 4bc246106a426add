"""docs/cli.md, the flag reference, is the parser's own --help: it fails when a flag changes and the
file was not rewritten (`bash scripts/cli_reference.sh`)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from rllock.orchestration.cli.main import build_parser, reference

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.skipif(sys.version_info[:2] != (3, 11), reason="argparse words its help differently by version")
def test_the_reference_is_the_parsers_help_as_it_is_now():
    assert (ROOT / "docs" / "cli.md").read_text() == reference(), "run: bash scripts/cli_reference.sh"


def test_the_reference_has_every_command_and_bench_and_follows_a_changed_flag():
    text = reference()
    commands = {a for a in build_parser()._subparsers._group_actions[0].choices}  # type: ignore[union-attr]
    assert {"solve", "train", "train-guide", "serve", "bench"} <= commands
    for command in commands:
        assert f"`rllock {command}`" in text
    for bench in ("checkers", "solve", "paper", "ablation", "scaling", "shapes", "serve", "guide"):
        assert f"`rllock bench {bench}`" in text
    assert "--time-limit" in text and "--no-such-flag" not in text
