"""`rllock bench ablation`: one cell per method and task, and Table 1's layout."""

from __future__ import annotations

import pytest
from helpers import run_cli, save_run

from rllock.errors import RLLockError
from rllock.orchestration.bench.ablation import ablation_cell, format_ablation_table, parse_ablation_tasks
from rllock.search.mcts import MCTSConfig
from rllock.search.network import NetConfig

NET = NetConfig(canvas=4, features=(4, 8))
FAST = MCTSConfig(simulations=2, max_considered=2, raw_samples=128, candidates=4, max_depth=4)


def test_ablation_cells_read_each_methods_run_and_the_table_has_table_1s_layout(tmp_path):
    runs = tmp_path / "runs"
    save_run(runs / "ppo" / "cube4-k7", "cube4", 7, net=NET, mcts=FAST, method="ppo", seconds=20 * 60)
    (task,) = parse_ablation_tasks("cube4-k7")
    cells = [
        ablation_cell(runs, method, task, count=1, batch=2, time_limit=1, seed=0)
        for method in ("rl-lock", "rl-lock-action", "ppo")
    ]
    assert [c.checkpoint is None for c in cells] == [True, True, False]  # only PPO has a run
    ppo = cells[2]
    assert ppo.training_minutes == 20.0 and ppo.episodes >= 2 and ppo.seconds > 0
    lines = format_ablation_table(cells, 60, "rllock bench ablation").splitlines()
    ours = next(line for line in lines if line.startswith("| cube4-k7 (ours) |"))
    assert ours.startswith("| cube4-k7 (ours) | 20.0 | ") and ours.endswith(
        "| not trained | - | not trained | - |"
    )
    paper = next(line for line in lines if line.startswith("| cube4-k7 (paper) |"))
    assert paper == "| cube4-k7 (paper) | 29.4 | none in 60 min | 62.4 | 0.01 | 33.0 | 0.05 |"
    save_run(runs / "rl-lock" / "cube4-k7", "cube4", 7, net=NET, mcts=FAST, method="ppo")
    with pytest.raises(RLLockError, match="holds a ppo checkpoint for K=7, not rl-lock"):
        ablation_cell(runs, "rl-lock", task, count=1, batch=2, time_limit=1, seed=0)


def test_bench_ablation_refuses_tasks_outside_table_1():
    code, _, err = run_cli("bench", "ablation", "--tasks", "sofa-k19")
    assert (
        code == 2 and "the ablation covers the nine cube tasks" in err and len(err.strip().splitlines()) == 1
    )
