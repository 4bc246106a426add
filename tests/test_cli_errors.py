"""Bad input: one line on stderr, exit status 2, no traceback."""

from __future__ import annotations

import argparse
import random
import shutil
from dataclasses import dataclass

import numpy as np
import pytest
from helpers import _fresh_cli, run_cli

from rllock.files.checkpoint import SHIPPED


def _files(tmp_path):
    (tmp_path / "malformed.puz").write_text("4 4 4\n1 2 x\n")
    (tmp_path / "short.vol").write_text("2 2 2\n1 1 1\n1 1 1\n")
    (tmp_path / "empty.puz").write_text("2 1 1\n0 0\n")
    (tmp_path / "apart.puz").write_text("3 1 1\n1 0 1\n")
    np.save(tmp_path / "flat.npy", np.ones((3, 3)))
    (tmp_path / "bad.json").write_text("{not json")


@pytest.mark.parametrize(
    "args,needle",
    [
        (["solve", "--shape", "teapot", "--pieces", "3"], "unknown shape"),
        (["solve", "--shape", "{t}/missing.puz", "--pieces", "3"], "no such file"),
        (["solve", "--shape", "{t}/malformed.puz", "--pieces", "3"], "malformed"),
        (["solve", "--shape", "{t}/short.vol", "--pieces", "3"], "malformed"),
        (["solve", "--shape", "{t}/empty.puz", "--pieces", "3"], "empty"),
        (["solve", "--shape", "{t}/apart.puz", "--pieces", "2"], "not 6-connected"),
        (["solve", "--shape", "{t}/flat.npy", "--pieces", "2"], "3-D"),
        (["solve", "--shape", "cube3", "--pieces", "1"], "at least 2"),
        (["solve", "--shape", "cube2", "--pieces", "9"], "larger than"),
        (["solve", "--shape", "cube3", "--pieces", "3", "--count", "0"], "--count"),
        (["verify", "{t}/bad.json"], "malformed"),
        (["verify", "{t}/nothing.puz"], "no such file"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tmp_path, args, needle):
    _files(tmp_path)
    args = [a.format(t=tmp_path) for a in args]
    if args[0] == "solve":
        args += ["--out", str(tmp_path / "out"), "--time-limit", "5"]
    code, _, err = run_cli(*args)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and needle in lines[0] and "Traceback" not in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "args,needle",
    [
        (
            ["train", "--shape", "cube4", "--pieces", "6", "--publish-every", "0"],
            "--publish-every must be positive",
        ),
        (
            ["train", "--shape", "cube4", "--pieces", "6", "--validation-episodes", "0"],
            "--validation-episodes",
        ),
        (["train", "--shape", "cube6", "--pieces", "6", "--canvas", "4"], "does not fit"),
        (["train", "--shape", "cube4", "--pieces", "6", "--success-fraction", "1.5"], "--success-fraction"),
        (["train", "--pieces", "6"], "--shape and --pieces"),
        (["train", "--tasks", "cube4:6-9", "--shape", "cube4"], "either --tasks"),
        (["train", "--tasks", "cube4:9-6"], "9-6"),
        (["train", "--tasks", "cube4:6", "--method", "ppo"], "rl-lock method only"),
        (["train", "--init", "cube4-k9", "--shape", "cube6", "--pieces", "20"], "canvas of the --init"),
        (
            ["train", "--init", "general", "--canvas", "4", "--shape", "cube5", "--pieces", "13"],
            "4^3 canvas; use a larger --canvas",
        ),
        (["bench", "transfer", "--checkpoint", "general", "--simulations", "0"], "--simulations must be"),
        (["bench", "success", "--checkpoint", "cube4-k8", "--episodes", "0"], "--episodes must be"),
        (["bench", "success", "--checkpoint", "general"], "name one with --shape and --pieces"),
        (["bench", "transfer", "--checkpoint", "{t}/nothing"], "no such checkpoint"),
        (["bench", "transfer", "--checkpoint", "cube4-k9"], "trained for one task"),
        (["train", "--resume", "{t}/nothing"], "cannot resume {t}/nothing: no such run directory"),
        (["train", "--resume", "{t}"], "holds no readable checkpoint"),
        (["generate", "--checkpoint", "{t}/nothing", "--out", "{t}/g"], "no such checkpoint"),
        (["generate", "--checkpoint", "{t}", "--batch", "0", "--out", "{t}/g"], "--batch"),
        (["bench", "selfplay", "--actors", "0"], "at least 1"),
        (["bench", "checkers", "--piece", "30"], "between 1 and K-1"),
    ],
)
def test_bad_training_and_inference_input_is_one_line_and_exit_2(tmp_path, args, needle):
    args = [a.format(t=tmp_path) for a in args]
    needle = needle.format(t=tmp_path)
    if args[0] == "train" and "--resume" not in args:
        args += ["--logdir", str(tmp_path / "run")]
    code, _, err = run_cli(*args)
    lines = err.strip().splitlines()
    assert code == 2 and needle in lines[-1] and "Traceback" not in err, err
    assert not (tmp_path / "run" / "checkpoints").exists()


def test_solve_refuses_an_output_folder_with_results(tmp_path):
    (tmp_path / "assembly_001").mkdir()
    code, _, err = run_cli("solve", "--shape", "cube3", "--pieces", "3", "--out", str(tmp_path))
    assert code == 2 and "already holds results" in err


def test_train_switches_parse_both_ways():
    from rllock.orchestration.cli.main import build_parser

    parser = build_parser()
    assert parser.parse_args(["train", "--shape", "cube4", "--pieces", "6"]).symmetries is True
    assert (
        parser.parse_args(["train", "--shape", "cube4", "--pieces", "6", "--no-symmetries"]).symmetries
        is False
    )


def test_learning_ratio_and_its_bound_when_the_baseline_finds_nothing():
    from rllock.orchestration.bench.learning import learning_ratio

    assert learning_ratio(10.0, 40.0, 200.0) == (0.25, None)
    assert learning_ratio(30.0, None, 300.0) == (None, 0.1)  # untrained: none in 300 s
    assert learning_ratio(None, 40.0, 200.0) == (None, None)
    assert learning_ratio(None, None, 200.0) == (None, None)


def _damaged_checkpoint(folder, damage: str):
    """A copy of the shipped cube4-k7 checkpoint whose array data files (state/**/d/*) are cut to a third
    or overwritten with random bytes of the same length."""
    shutil.copytree(SHIPPED / "cube4-k7", folder)
    rng = random.Random(0)
    files = [f for f in (folder / "state").rglob("*") if f.is_file() and f.parent.name == "d"]
    assert files, "the checkpoint layout changed: no array data files to damage"
    for f in files:
        size = f.stat().st_size
        f.write_bytes(f.read_bytes()[: size // 3] if damage == "truncated" else rng.randbytes(size))
    return folder


@pytest.mark.parametrize("damage", ["truncated", "garbled"])
@pytest.mark.parametrize("command", ["generate", "bench learning"])
def test_a_damaged_checkpoint_is_one_line(tmp_path, damage, command):
    # The failed restore used to print tracebacks from orbax's closed event loop after the error line.
    folder = _damaged_checkpoint(tmp_path / "ckpt", damage)
    extra = ["--out", str(tmp_path / "out")] if command == "generate" else ["--count", "1"]
    code, _, err = run_cli(*command.split(), "--checkpoint", str(folder), *extra)
    assert code == 2 and err.count("\n") == 1, err[:3000]
    assert err.startswith(f"rllock: error: checkpoint {folder} is corrupted or unreadable: "), err
    assert not (tmp_path / "out").exists()


def test_garbled_metadata_is_one_line(tmp_path):
    folder = shutil.copytree(SHIPPED / "cube4-k7", tmp_path / "ckpt")
    (folder / "meta" / "metadata").write_bytes(b"\xe1\x80{")  # not UTF-8
    code, _, err = run_cli("generate", "--checkpoint", str(folder), "--out", str(tmp_path / "out"))
    assert code == 2 and err.count("\n") == 1 and "is corrupted or unreadable" in err, err


def test_a_checkpoint_for_another_task_is_refused_in_words(tmp_path):
    code, _, err = run_cli(
        "generate",
        "--checkpoint",
        "cube4-k7",
        "--shape",
        "cube5",
        "--pieces",
        "13",
        "--out",
        str(tmp_path / "o"),
    )
    assert code == 2 and err.count("\n") == 1, err
    assert err.rstrip().endswith(
        "was made for another task: cube4 (4x4x4) K=7, removal straight; this task is cube5 (5x5x5) K=13, "
        "removal straight"
    ), err


def test_another_canvas_or_grid_is_named_where_the_words_would_be_equal():
    from rllock.core.env import make_task
    from rllock.core.identity import check_same_task, task_identity
    from rllock.errors import RLLockError

    cube = task_identity(make_task("cube4", 7), 4)
    with pytest.raises(RLLockError, match=r"K=7, removal straight, on a 4\^3 canvas; this task .* on a 8\^3"):
        check_same_task(cube, {**cube, "canvas": 8}, SHIPPED)
    with pytest.raises(RLLockError, match="but another shape of that name and size"):
        check_same_task(cube, {**cube, "grid_sha256": "0" * 64}, SHIPPED)
    check_same_task(cube, dict(cube), SHIPPED)  # the same task passes


def test_removal_alone_is_checked_against_the_checkpoint(tmp_path):
    code, _, err = run_cli(
        "generate", "--checkpoint", "cube4-k7", "--removal", "path", "--out", str(tmp_path / "o")
    )
    assert code == 2 and err.count("\n") == 1, err
    assert err.rstrip().endswith("K=7, removal straight; this task is cube4 (4x4x4) K=7, removal path"), err
    assert not (tmp_path / "o").exists()


def test_removal_alone_names_the_checkpoints_own_task():
    from rllock.core.identity import check_same_task
    from rllock.files.checkpoint import open_checkpoint
    from rllock.search.serving import Named

    meta = open_checkpoint("cube4-k7").metadata
    named = Named(removal="straight")
    check_same_task(meta.task, named.identity(meta), SHIPPED)  # its own mode: accepted
    assert Named().identity(meta) is None
    assert Named(removal="path").identity(meta)["removal"] == "path"


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "0", "-3"])
def test_time_limit_must_be_positive_and_finite(tmp_path, value):
    from rllock.orchestration.cli.common import positive_float

    with pytest.raises(argparse.ArgumentTypeError, match="positive finite"):
        positive_float(value)
    code, _, err = run_cli(
        "solve", "--shape", "cube3", "--pieces", "3", f"--time-limit={value}", "--out", str(tmp_path / "o")
    )
    assert code == 2 and f"--time-limit: must be a positive finite number, got {value}" in err, err
    assert not (tmp_path / "o").exists()


def test_time_limit_takes_a_positive_number():
    from rllock.orchestration.cli.common import positive_float

    assert positive_float("2.5") == 2.5


def test_the_forked_command_answers_as_a_fresh_interpreter_does(data, tmp_path, monkeypatch):
    """`run_cli` forks the command from a process that imported it (`tests/cli_server.py`): the same
    exit status, stdout and stderr as `python -m rllock.orchestration.cli` in a new interpreter, also where
    the command reads its working folder."""
    (tmp_path / "bad.json").write_text("{not json")
    cube = str(data / "published" / "Cube_4x4x4_K9.puz")
    monkeypatch.chdir(tmp_path)
    for args in (
        ("verify", cube, "--removal", "path", "--json"),
        ("verify", cube, "--json"),
        ("verify", "bad.json"),
        ("solve", "--shape", "teapot", "--pieces", "3", "--out", "out"),
        ("frobnicate",),
    ):
        forked, fresh = run_cli(*args), _fresh_cli(args, 120)
        assert forked == fresh and forked[0] in (0, 1, 2), (args, forked, fresh)


def _parsers(parser: argparse.ArgumentParser, name: str = "rllock"):
    yield name, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for command, sub in action.choices.items():
                yield from _parsers(sub, f"{name} {command}")


@dataclass(frozen=True)
class _Shares:
    share: float = 0.5
    """at most 50% of the restarts"""


def test_every_commands_help_prints_with_its_flags_docs_as_written():
    """argparse formats help strings with %: a config docstring's "2%" broke `train-guide --help`."""
    from rllock.orchestration.cli.flags import add_flags
    from rllock.orchestration.cli.main import build_parser

    helps = {name: parser.format_help() for name, parser in _parsers(build_parser())}
    assert {"rllock solve", "rllock train-guide", "rllock bench guide"} <= set(helps)
    assert "the next K whose last piece is under twice the others" in " ".join(
        helps["rllock train-guide"].split()
    )
    parser = argparse.ArgumentParser()
    add_flags(parser, _Shares)
    assert "at most 50% of the restarts" in parser.format_help()
