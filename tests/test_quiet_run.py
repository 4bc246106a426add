"""A successful training run is quiet: stderr holds the trainer's own INFO lines and nothing else; no
warnings from Ray or JAX that the run is fine without."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tempfile

import pytest
from helpers import tiny_flags

pytestmark = [pytest.mark.slow, pytest.mark.ray]

# What a successful run printed before: Ray retrying the calls of the actors it was told to kill, with a
# raw colour code; Ray doubting the actors' restarts; JAX's warning of a fork after its threads started;
# Ray's notice that it uses token authentication, its default.
NOISE = (
    "killed by `ray.kill`",
    "(raylet)",
    "\x1b[",
    "core_worker.cc",
    "constructor arguments in the object store",
    "os.fork() was called",
    "RuntimeWarning",
    "Token authentication",
)
OUR_LINE = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d+ INFO (orchestration|learner|actors|rllock)\.")


def test_a_short_training_run_prints_only_its_own_lines(tmp_path):
    logdir = tmp_path / "run"
    # The address file a `ray start` (or a test's Cluster) leaves behind, here of a cluster long gone: a
    # run without --address starts its own Ray instead of joining it. A short folder: Ray's socket paths
    # under it must stay within the 107 characters a Unix socket allows.
    ray_tmp = tempfile.mkdtemp(prefix="rq", dir="/tmp")
    os.makedirs(f"{ray_tmp}/ray")
    with open(f"{ray_tmp}/ray/ray_current_cluster", "w") as f:
        f.write("127.0.0.1:9")
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"} | {"RAY_TMPDIR": ray_tmp}
    # Ends on its step limit with a self-play batch in flight, which the shutdown must drop quietly. The
    # minutes are only a ceiling: a fresh CI machine under the other test worker's load took more than the
    # 1 minute this once had without finishing a self-play batch (Ray's start counts in it).
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "orchestration.cli", "train", *tiny_flags(), "--minutes", "4"]
            + ["--max-learner-steps", "5", "--logdir", str(logdir)],
            capture_output=True,
            text=True,
            timeout=420,
            env=env,
        )
    finally:
        shutil.rmtree(ray_tmp, ignore_errors=True)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("train: 5 learner steps")
    for needle in NOISE:
        assert needle not in proc.stderr, f"{needle!r} in:\n{proc.stderr}"
    lines = proc.stderr.strip().splitlines()
    assert lines and all(OUR_LINE.match(line) for line in lines), proc.stderr
    assert "tensorboard" not in proc.stdout  # the one next step is the demo's last line, not one per command
