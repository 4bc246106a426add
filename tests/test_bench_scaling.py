"""`rllock bench scaling`: its plan fitted to the machine, and the workstation preset run small on this
machine's cores, on one node and on three, through the command line."""

from __future__ import annotations

import json

import pytest
from helpers import run_cli

from rllock.orchestration.bench.scaling import PRESETS, fit_to_machine


def test_the_plan_fits_the_machine_it_runs_on():
    workstation = PRESETS["workstation"]
    assert fit_to_machine(workstation, 16).actors == (1, 4, 8, 15)  # the workstation runs it all
    assert fit_to_machine(workstation, 2).actors == (1, 2)  # the largest that fits is kept
    assert fit_to_machine(workstation, 6).actors == (1, 4, 6)
    # three nodes need two worker nodes with a core each
    assert fit_to_machine(PRESETS["small"], 2).nodes == (1, 3)
    assert fit_to_machine(PRESETS["small"], 1).nodes == (1,)


@pytest.mark.slow
@pytest.mark.ray
def test_the_workstation_preset_runs_small_on_this_machine_over_three_nodes():
    small = ["--shape", "box:4x4x2", "--pieces", "3", "--simulations", "8", "--episodes-per-batch", "2",
             "--features", "4,8"]  # fmt: skip
    code, out, err = run_cli(
        "bench", "scaling", "--preset", "workstation", *small, "--actors", "2", "--nodes", "3",
        "--seconds", "2", "--learner-steps", "2", "--json", timeout=400,
    )  # fmt: skip
    assert code == 0, out + err
    report = json.loads(out)
    assert report["plan"]["features"] == [4, 8] and report["canvas"] == 4
    rows = {(r["nodes"], r["actors"]): r for r in report["rows"]}
    assert set(rows) == {(3, a) for a in report["plan"]["actors"]}
    for (nodes, actors), row in rows.items():
        assert row["episodes"] > 0 and row["episodes_per_sec"] > 0 and row["learner_steps_per_sec"] > 0
        # the episodes' arrays cross the object store: at least their labels, one byte per voxel a step
        assert row["bytes_per_episode"] > 32
        assert row["param_bytes"] > 0 and row["broadcast_ms"] > 0 and row["call_ms"] > 0
        assert row["actor_nodes"] == min(actors, nodes - 1)  # spread over the worker nodes
    assert report["learner_alone_steps_per_sec"]["cpu"] > 0
