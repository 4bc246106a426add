"""The project's structure: layers, the public API, and flags generated from the one config."""

from __future__ import annotations

import argparse
import ast
import subprocess
import sys
from pathlib import Path

import pytest

from rllock.config import MCTSConfig, NetConfig, SelfPlayConfig, TrainConfig, from_flat, from_json, to_json
from rllock.flags import add_flags, field_docs, from_flags

ROOT = Path(__file__).resolve().parents[1]
UPPER = {
    "actors": {"orchestration"},
    "learner": {"orchestration", "actors"},
    "rllock": {"actors", "learner", "orchestration"},
}


def _module_level_imports(path: Path) -> set[str]:
    """Top-level packages imported at module level (not inside functions)."""
    found = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.Import):
            found |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module.split(".")[0])
    return found


@pytest.mark.parametrize("package", sorted(UPPER))
def test_no_module_level_import_goes_up_a_layer(package):
    offenders = {
        str(p.relative_to(ROOT)): _module_level_imports(p) & UPPER[package]
        for p in (ROOT / package).rglob("*.py")
    }
    assert not {k: v for k, v in offenders.items() if v}


def test_the_public_api_is_light_and_complete():
    code = (
        "import sys, rllock; assert 'jax' not in sys.modules and 'ray' not in sys.modules; "
        "print(sorted(n for n in rllock.__all__ if callable(getattr(rllock, n))))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == str(["generate", "load_policy", "make_task", "read_assembly", "solve", "verify"])


def test_api_solve_returns_verified_assemblies():
    import rllock

    task = rllock.make_task("cube4", 7)
    found = rllock.solve(task, count=2, time_limit=30, seed=1)
    assert len(found) == 2 and all(rllock.verify(a).valid for a in found)
    assert not (found[0] == found[1]).all()


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser()
    add_flags(p, TrainConfig, required_unless="--resume")
    return p


def test_flags_come_from_the_config_with_their_docstrings():
    parser = _parser()
    helps = {a.dest: a.help for a in parser._actions}
    assert "Simulations per decision" in helps["simulations"]  # a nested field, flat flag
    assert helps["evaluation"].startswith(field_docs(SelfPlayConfig)["evaluation"][:40])
    args = parser.parse_args(
        [
            "--shape",
            "cube5",
            "--pieces",
            "13",
            "--features",
            "8,16",
            "--simulations",
            "32",
            "--no-symmetries",
            "--episodes-per-batch",
            "4",
            "--max-learner-steps",
            "7",
        ]
    )
    config = from_flags(TrainConfig, args)
    assert config.net == NetConfig(features=(8, 16)) and config.mcts == MCTSConfig(simulations=32)
    assert config.learner.symmetries is False and config.selfplay.episodes_per_batch == 4
    assert config.max_learner_steps == 7 and config.net.canvas is None


def test_the_saved_config_round_trips():
    config = TrainConfig(
        shape="ring",
        pieces=15,
        net=NetConfig(canvas=8, features=(4, 8)),
        mcts=MCTSConfig(candidates=16),
        selfplay=SelfPlayConfig(actors=3),
    )
    assert from_json(TrainConfig, to_json(config)) == config


def test_version_one_checkpoints_flat_settings_become_the_nested_config():
    flat = {
        "shape": "cube4",
        "pieces": 8,
        "canvas": 4,
        "features": [8, 16],
        "simulations": 64,
        "actors": 2,
        "episodes_per_batch": 4,
        "learning_rate": 3e-4,
        "min_buffer": 256,
        "unknown_old_field": 1,
    }
    config = from_flat(TrainConfig, flat)
    assert config.net == NetConfig(canvas=4, features=(8, 16)) and config.mcts.simulations == 64
    assert config.selfplay == SelfPlayConfig(actors=2, episodes_per_batch=4)
    assert config.learner.learning_rate == 3e-4 and config.min_buffer == 256


def test_layouts_give_each_actor_its_share_of_the_cores():
    from orchestration.pool import plan_layout

    per_actor = plan_layout(SelfPlayConfig(), cpus=16, gpus=0, reserved_cpus=1)
    assert (per_actor.actors, per_actor.threads, per_actor.groups, per_actor.mode) == (15, 1, 1, "per-actor")
    one = plan_layout(SelfPlayConfig(actors=1), cpus=2, gpus=0, reserved_cpus=0)
    assert (one.cpus, one.threads, one.groups) == (2, 2, 2)
    crowded = plan_layout(SelfPlayConfig(actors=4), cpus=2, gpus=0, reserved_cpus=1)
    assert crowded.cpus == 0.25 and crowded.threads == 1  # more actors than cores: they share
    gpu = plan_layout(SelfPlayConfig(), cpus=16, gpus=1, reserved_cpus=1)
    assert (gpu.mode, gpu.actors, gpu.episodes, gpu.gpus, gpu.groups) == ("lockstep", 1, 15 * 8, 1.0, 1)
    cluster = plan_layout(
        SelfPlayConfig(evaluation="lockstep"), cpus=64, gpus=1, reserved_cpus=1, node_cpus=16
    )
    assert cluster.cpus == 16 and cluster.threads == 16  # one worker fits on one node
