"""`rllock bench shapes` and `general` beyond its 8^3 canvas."""

from __future__ import annotations

import json
import logging

import pytest
from helpers import run_cli, save_multitask_run

from rllock.config import MCTSConfig, NetConfig
from rllock.core.env import make_task
from rllock.core.verifier import verify_labels
from rllock.errors import RLLockError
from rllock.files.assembly import read_assembly
from rllock.search.inference import generate, load_policy
from rllock.search.serving import MAX_CANVAS


def test_general_plays_a_shape_larger_than_its_canvas_on_the_smallest_canvas_that_fits():
    task = make_task("box:9x3x2", 3)  # 9 > 8: general's own 8^3 canvas is too small
    policy = load_policy("general", task)
    assert policy.net.canvas == 12  # the next multiple of the U-Net's level step
    assert load_policy("general", make_task("cube5", 13)).net.canvas == 8  # its own where it fits
    with pytest.raises(RLLockError, match=f"largest canvas .* plays on \\({MAX_CANVAS}\\^3\\)"):
        load_policy("general", make_task(f"box:{MAX_CANVAS + 1}x2x2", 4))


def test_a_checkpoint_trained_on_several_canvases_plays_each_shape_on_the_smallest_that_fits(
    tmp_path, caplog
):
    net = NetConfig(canvas=4, features=(4, 8))
    save_multitask_run(tmp_path / "run", "cube3:3,box:5x4x3:4@8", net=net, mcts=MCTSConfig(simulations=4))
    with caplog.at_level(logging.INFO, logger="rllock.search.inference"):
        assert load_policy(tmp_path / "run", make_task("cube4", 4)).net.canvas == 4
        assert load_policy(tmp_path / "run", make_task("box:6x2x2", 3)).net.canvas == 8
        assert "was trained on" not in caplog.text  # 4^3 and 8^3 are its own canvases
        assert load_policy(tmp_path / "run", make_task("box:9x2x2", 3)).net.canvas == 10
    assert "was trained on 4^3, 8^3 canvases; it plays box:9x2x2 on 10^3" in caplog.text


@pytest.mark.slow
def test_general_generates_verified_assemblies_zero_shot_on_a_larger_canvas(tmp_path):
    task = make_task("box:9x3x2", 3)
    policy = load_policy("general", task)
    result = generate(policy, count=1, batch=4, time_limit=120, seed=0, out=tmp_path, progress=False)
    assert result.valid >= 1
    labels, _ = read_assembly(next(tmp_path.glob("*/assembly.json")))
    assert labels.shape == (9, 3, 2) and verify_labels(labels, "straight").valid


@pytest.mark.slow
def test_bench_shapes_sweeps_k_and_says_impossible_none_or_seconds():
    code, out, err = run_cli(
        "bench", "shapes", "--shapes", "box:9x3x2,box:6x6x1", "--pieces", "3,200", "--arms", "solver,general",
        "--workers", "1,2", "--time-limit", "60", "--simulations", "8", "--batch", "4", "--json", timeout=400,
    )  # fmt: skip
    assert code == 0, out + err
    rows = {(r["shape"], r["pieces"]): r["cells"] for r in json.loads(out)["rows"]}
    assert set(rows) == {("box:9x3x2", 3), ("box:6x6x1", 3)}  # K = 200 > N: skipped
    flat = rows[("box:6x6x1", 3)]  # one voxel thick: no piece can be locked along z
    assert flat["solver"]["impossible"] and flat["solver x2"]["impossible"] and flat["general"]["impossible"]
    solved = rows[("box:9x3x2", 3)]
    assert all(0 < solved[arm]["seconds"] < 60 for arm in ("solver", "solver x2", "general"))


def test_bench_shapes_refuses_an_unknown_shape_in_one_line():
    code, out, err = run_cli("bench", "shapes", "--shapes", "nosuch", "--arms", "solver")
    assert code == 2 and out == "" and err.startswith("rllock: error: unknown shape 'nosuch'")
    assert len(err.strip().splitlines()) == 1
