"""Shipped checkpoints: what `ship` keeps, how names resolve, and that every shipped one loads."""

from __future__ import annotations

import json
import re

import jax
import numpy as np
import orbax.checkpoint as ocp
import pytest
from helpers import run_cli, save_run

from rllock.core.env import make_task
from rllock.errors import RLLockError
from rllock.files import checkpoint as ckpt
from rllock.orchestration.bench.paper import bench_paper_task, format_paper_table, parse_paper_tasks, row_json
from rllock.orchestration.cli.main import main
from rllock.search import pretrained
from rllock.search.guide_checkpoint import shipped_guides
from rllock.search.inference import (
    SuccessRate,
    load_policy,
    local_groups,
    play_round,
    searchers_for,
    success_rate,
)
from rllock.search.mcts import MCTSConfig
from rllock.search.network import NetConfig

NET = NetConfig(canvas=4, features=(4, 8))
MCTS = MCTSConfig(simulations=8, max_considered=4, raw_samples=256, candidates=8)


@pytest.fixture()
def run(tmp_path):
    """A run directory with one checkpoint (params, optimizer state, provenance), and its learner."""
    validation = {"success_rate": 0.25, "episodes": 8}
    learner = save_run(tmp_path / "run", "box:4x4x2", 4, net=NET, mcts=MCTS, validation=validation)
    return tmp_path / "run", learner


def test_ship_keeps_the_parameters_and_metadata_only(run, tmp_path):
    source, learner = run
    target = pretrained.ship(source, "box-k4", into=tmp_path / "shipped")
    saved = ocp.PyTreeCheckpointer().restore((target / "state").absolute())
    assert set(saved) == {"params"}  # no optimizer state, step or PRNG key
    for a, b in zip(jax.tree_util.tree_leaves(saved["params"]), jax.tree_util.tree_leaves(learner.params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    row = pretrained.describe("box-k4", tmp_path / "shipped")
    assert row["task"] == "box:4x4x2 K=4" and row["learner_steps"] == 7 and row["training_minutes"] == 10.0
    assert row["validation_success"] == 0.25 and row["machine"]
    with pytest.raises(RLLockError, match="bad checkpoint name"):
        pretrained.ship(source, "Box K4", into=tmp_path / "shipped")


def test_a_shipped_name_resolves_where_no_such_path_exists(run, tmp_path, monkeypatch):
    source, learner = run
    shipped = tmp_path / "shipped"
    pretrained.ship(source, "box-k4", into=shipped)
    monkeypatch.setattr(ckpt, "SHIPPED", shipped)
    monkeypatch.chdir(tmp_path)
    policy = load_policy("box-k4")
    assert policy.step == 7 and policy.task.pieces == 4 and policy.source == str(shipped / "box-k4")
    (tmp_path / "box-k4").mkdir()  # a path of that name wins over the shipped name
    with pytest.raises(RLLockError, match="holds no RL-Lock checkpoint"):
        load_policy("box-k4")
    with pytest.raises(RLLockError, match=r"no such checkpoint directory or shipped checkpoint.*box-k4"):
        load_policy("cube9-k3")


def test_a_fine_tuned_checkpoint_lists_what_it_started_from(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(ckpt, "SHIPPED", tmp_path / "shipped")
    monkeypatch.setattr("rllock.search.guide_checkpoint.GUIDES", tmp_path / "shipped" / "guides")
    save_run(tmp_path / "scratch", "box:4x4x2", 4, net=NET, mcts=MCTS, seconds=1200.0)
    save_run(tmp_path / "tuned", "box:4x4x2", 5, net=NET, mcts=MCTS, seconds=300.0, init="general")
    pretrained.ship(tmp_path / "scratch", "box-k4")
    pretrained.ship(tmp_path / "tuned", "box-k5")
    assert pretrained.describe("box-k4")["init"] is None
    assert pretrained.describe("box-k5")["init"] == "general"
    assert main(["pretrained"]) == 0
    out = capsys.readouterr().out
    rows = {line.split(" | ")[0].strip("| "): line.split(" | ")[4] for line in out.splitlines()[2:]}
    assert rows == {"box-k4": "20.0", "box-k5": "5.0 from general"}


def test_every_shipped_checkpoint_loads_for_the_task_its_name_says():
    names = ckpt.shipped_names()
    total = sum(f.stat().st_size for f in ckpt.SHIPPED.rglob("*") if f.is_file()) if names else 0
    assert total < 40 * 2**20  # the package stays small
    for name in names:
        if ckpt.read_metadata(ckpt.SHIPPED / name).multitask:  # `general`: any task on its canvas
            policy = load_policy(name, make_task("cube4", 8))
            assert policy.net.task_planes and policy.task.pieces == 8, name
        else:
            shape, k = re.fullmatch(r"([a-z0-9]+)-k([0-9]+)", name).groups()
            policy = load_policy(name)
            assert policy.task.pieces == int(k) and policy.task.shape_name == shape, name
        row = pretrained.describe(name)
        assert row["commit"] and row["training_minutes"] > 0 and row["learner_steps"] > 0, name
    code, out, err = run_cli("pretrained", "--json")
    assert code == 0, err
    listed = json.loads(out)
    assert [r["name"] for r in listed if r.get("kind") != "guide"] == names
    assert [r["name"] for r in listed if r.get("kind") == "guide"] == shipped_guides()


def test_bench_paper_runs_the_three_arms_beside_the_papers_figures(tmp_path, monkeypatch):
    fast = MCTSConfig(simulations=2, max_considered=2, raw_samples=128, candidates=4)
    save_run(tmp_path / "run", "cube4", 7, net=NET, mcts=fast, step=11)
    monkeypatch.setattr(ckpt, "SHIPPED", tmp_path / "shipped")
    pretrained.ship(tmp_path / "run", "cube4-k7")
    (task,) = parse_paper_tasks("cube4-k7")
    row = bench_paper_task(task, count=1, batch=2, time_limit=1, seed=0)
    assert row.checkpoint == "cube4-k7" and row.step == 11
    assert row.trained.episodes >= 2 and row.untrained.episodes >= 2
    assert row.solver.valid == 1  # the solver finds a 4^3 K=7 assembly in well under a second
    doc = row_json(row)
    assert doc["paper_rllock_s"] == 0.05 * 60 and doc["solver"]["time_per_valid_s"] == row.solver.seconds
    protocol = dict(count=1, batch=2, time_limit=1)
    lines = format_paper_table([row], protocol, "rllock bench paper --tasks cube4-k7").splitlines()
    assert lines[0].strip() == "rllock bench paper --tasks cube4-k7"
    assert "1 wanted, batches of 2, 1 s limit per arm" in lines[2]
    assert any(line.startswith("| cube4-k7 | ") and line.endswith("| 3.0 | 0.6 |") for line in lines)


def test_bench_paper_refuses_an_unknown_task():
    code, _, err = run_cli("bench", "paper", "--tasks", "cube4-k6")
    assert code == 2 and "unknown task 'cube4-k6'" in err and len(err.strip().splitlines()) == 1


def test_the_pretrained_table_names_the_training_machine_briefly():
    assert pretrained.machine_summary("2 x AMD EPYC, cpu (cpu)") == "2 cores"
    gpu = "16 x Intel(R) Xeon(R) Processor, gpu (NVIDIA H100 80GB HBM3)"
    assert pretrained.machine_summary(gpu) == "16 cores, NVIDIA H100 80GB HBM3"
    assert pretrained.machine_summary(None) == "-"
    assert pretrained.machine_summary("a laptop") == "a laptop"  # an unknown form is shown as it is


def test_the_success_interval_is_wilsons():
    assert SuccessRate(5, 10, 1.0).interval() == pytest.approx((0.2366, 0.7634), abs=1e-4)
    low, high = SuccessRate(0, 64, 1.0).interval()
    assert low == 0.0 and high == pytest.approx(1.96**2 / (64 + 1.96**2))  # none of 64: still up to 5.7%
    a, b = SuccessRate(3, 64, 1.0).interval()
    c, d = SuccessRate(61, 64, 1.0).interval()
    assert (a, b) == pytest.approx((1 - d, 1 - c)) and a < 3 / 64 < b


def test_bench_success_counts_every_valid_episode_of_whole_rounds(run):
    source, _ = run
    policy = load_policy(source)
    r = success_rate(policy, episodes=9, batch=8, seed=3)
    groups = searchers_for(policy, 8, local_groups())
    reference = [e.success for i in range(2) for e in play_round(groups, policy, 3, i)]
    assert r.episodes == len(reference) == 16 and r.valid == sum(reference) > 0
    code, out, err = run_cli(
        "bench", "success", "--checkpoint", str(source), "--checkpoint", "box-k4-missing", "--episodes", "8",
    )  # fmt: skip
    assert code == 2 and "no such checkpoint directory" in err and len(err.strip().splitlines()) == 1
    code, out, err = run_cli(
        "bench", "success", "--checkpoint", str(source), "--checkpoint", str(source), "--episodes", "3",
        "--batch", "8", "--seed", "3", "--simulations", "4", "--json",
    )  # fmt: skip
    assert code == 0, err
    rows = json.loads(out)
    assert [(row["simulations"], row["episodes"], row["task"]) for row in rows] == [
        (4, 8, "box:4x4x2 K=4")
    ] * 2
    assert rows[0]["valid"] == rows[1]["valid"]  # the same seeds for every checkpoint
