"""The whole trainer on a real local Ray instance (num_cpus=2), on a tiny task, then generate from it."""

from __future__ import annotations

import dataclasses
import json
import math

import pytest
import ray
from helpers import TINY, run_cli
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from rllock.errors import RLLockError
from rllock.orchestration.train import train

pytestmark = [pytest.mark.slow, pytest.mark.ray]
STEPS = 30


_RUNS: dict[str, tuple] = {}


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    # Kept beyond the fixture: under xdist the worker tore this module fixture down between the module's
    # tests and trained again; the run's folder outlives the teardown.
    if "run" not in _RUNS:
        logdir = tmp_path_factory.mktemp("run")
        ray.init(address="local", num_cpus=2, include_dashboard=False)  # not a cluster left on the machine
        try:
            # The run ends on its learner-step limit; the minutes are only a safety net.
            result = train(dataclasses.replace(TINY, minutes=5, max_learner_steps=STEPS, logdir=str(logdir)))
        finally:
            ray.shutdown()
        _RUNS["run"] = (logdir, result)
    return _RUNS["run"]


def test_training_writes_checkpoints_and_event_files(run):
    logdir, result = run
    assert result.steps == STEPS and result.episodes > 0
    latest = sorted(int(p.name) for p in (logdir / "checkpoints").iterdir() if p.name.isdigit())
    best = [p for p in (logdir / "best").iterdir() if p.name.isdigit()]
    assert latest and latest[-1] == result.steps and len(best) == 1
    meta = json.loads((logdir / "checkpoints" / str(latest[-1]) / "meta" / "metadata").read_text())
    assert meta["task"]["pieces"] == 3 and meta["step"] == result.steps
    events = EventAccumulator(str(logdir))
    events.Reload()
    tags = set(events.Tags()["scalars"])
    assert {
        "losses/policy",
        "losses/value",
        "charts/episodes_per_sec",
        "charts/simulations_per_sec",
        "charts/policy_lag",
        "charts/learner_steps_per_sec",
        "buffer/size",
        "validation/success_rate",
        "validation/mean_return",
        "validation/time_per_valid_s",
    } <= tags
    assert "best/assembly" in events.Tags()["images"] and events.Tags()["tensors"]  # picture; config text
    for tag in ("charts/episodes_per_sec", "validation/success_rate"):
        steps = [e.step for e in events.Scalars(tag)]
        assert steps == sorted(steps) and steps[-1] == result.steps
    assert max(e.value for e in events.Scalars("charts/policy_lag")) <= TINY.max_policy_lag
    for kind in ("driver", "buffer", "actor"):
        assert events.Scalars(f"memory/{kind}_peak_mb")[-1].value > 50  # real processes, real megabytes
    assert (logdir / "best_assembly" / "assembly.json").exists() and (logdir / "replay.npz").exists()
    losses = [e.value for e in events.Scalars("losses/policy")] + [
        e.value for e in events.Scalars("losses/value")
    ]
    assert losses and all(math.isfinite(v) for v in losses)


def test_generate_from_the_run_writes_verified_assemblies(run, tmp_path):
    logdir, _ = run
    code, out, err = run_cli(
        "generate",
        "--checkpoint",
        str(logdir),
        "--count",
        "1",
        "--batch",
        "8",
        "--time-limit",
        "120",
        "--out",
        str(tmp_path / "gen"),
    )
    assert code == 0, err
    doc = json.loads((tmp_path / "gen" / "assembly_001" / "assembly.json").read_text())
    assert doc["verification"]["valid"] and doc["method"]["name"] == "rl-lock" and doc["K"] == 3
    code, _, err = run_cli(
        "generate",
        "--checkpoint",
        str(logdir),
        "--shape",
        "box:4x4x2",
        "--pieces",
        "4",
        "--out",
        str(tmp_path / "other"),
    )
    assert code == 2 and "another task" in err and "Traceback" not in err


def test_a_used_logdir_is_refused(run):
    logdir, _ = run
    with pytest.raises(RLLockError, match="already holds"):
        train(dataclasses.replace(TINY, minutes=0.1, logdir=str(logdir)))


def test_generate_on_ray_actors_writes_verified_distinct_assemblies(run, tmp_path):
    logdir, _ = run
    out = tmp_path / "gen"
    code, stdout, err = run_cli(
        "generate",
        "--checkpoint",
        str(logdir),
        "--count",
        "2",
        "--batch",
        "8",
        "--time-limit",
        "120",
        "--actors",
        "2",
        "--out",
        str(out),
    )
    assert code == 0, err
    docs = [json.loads((out / f"assembly_00{i}" / "assembly.json").read_text()) for i in (1, 2)]
    assert all(d["verification"]["valid"] and d["method"]["name"] == "rl-lock" for d in docs)
    assert docs[0]["labels"] != docs[1]["labels"] and (out / "assembly_001" / "assembly.png").exists()
