"""`rllock bench ablation`: one cell per method and task, and Table 1's layout."""

from __future__ import annotations

import json

from helpers import run_cli, save_run

from rllock.mcts import MCTSConfig
from rllock.network import NetConfig

NET = NetConfig(canvas=4, features=(4, 8))
FAST = MCTSConfig(simulations=2, max_considered=2, raw_samples=128, candidates=4, max_depth=4)


def test_bench_ablation_reads_each_methods_run_and_prints_table_1(tmp_path):
    runs = tmp_path / "runs"
    for method, minutes in (("rl-lock", 10.0), ("ppo", 20.0)):  # no rl-lock-action run: "not trained"
        save_run(
            runs / method / "cube4-k7", "cube4", 7, net=NET, mcts=FAST, method=method, seconds=minutes * 60
        )
    table = tmp_path / "table.md"
    args = ["--runs", str(runs), "--tasks", "cube4-k7", "--count", "1", "--batch", "2", "--time-limit", "1"]
    code, out, err = run_cli("bench", "ablation", *args, "--json", "--out", str(table))
    assert code == 0, err
    cells = {c["method"]: c for c in json.loads(out)}
    assert cells["rl-lock"]["training_minutes"] == 10.0 and cells["ppo"]["training_minutes"] == 20.0
    assert cells["rl-lock-action"]["checkpoint"] is None
    for method in ("rl-lock", "ppo"):
        assert cells[method]["episodes"] >= 2 and cells[method]["seconds"] > 0
    lines = table.read_text().splitlines()
    ours = next(line for line in lines if line.startswith("| cube4-k7 (ours) |"))
    assert ours.startswith("| cube4-k7 (ours) | 20.0 | ") and "| not trained | - |" in ours
    paper = next(line for line in lines if line.startswith("| cube4-k7 (paper) |"))
    assert paper == "| cube4-k7 (paper) | 29.4 | none in 60 min | 62.4 | 0.01 | 33.0 | 0.05 |"
    code, _, err = run_cli("bench", "ablation", "--runs", str(runs), "--tasks", "sofa-k19")
    assert code == 2 and "the ablation covers the nine cube tasks" in err
