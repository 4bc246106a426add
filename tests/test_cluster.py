"""Training against a real Ray head started with `ray start --head` on loopback, through the cluster
entry point, as `ray submit` and Ray Jobs run it."""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import yaml
from helpers import tiny_flags

from cluster.train_job import job_args

TINY = tiny_flags()

ROOT = Path(__file__).resolve().parents[1]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_job_args_join_the_cluster_unless_told_otherwise():
    assert job_args(["--shape", "cube6"]) == ["train", "--shape", "cube6", "--address", "auto"]
    assert job_args(["--address", "10.0.0.1:6379"]) == ["train", "--address", "10.0.0.1:6379"]


def test_a_ray_job_keeps_its_run_folder_out_of_the_temporary_working_dir(tmp_path):
    home = tmp_path / "home"
    assert job_args(["--logdir", "runs/a"], in_job=True, home=home)[1:3] == ["--logdir", str(home / "runs/a")]
    assert job_args(["--resume=runs/a"], in_job=True, home=home)[1] == f"--resume={home / 'runs/a'}"
    assert job_args(["--logdir", "/abs/run"], in_job=True, home=home)[1:3] == ["--logdir", "/abs/run"]
    # the default folder too; outside a job, nothing changes
    assert job_args(["--shape", "cube6"], in_job=True, home=home)[-2:] == [
        "--logdir",
        str(home / "runs/latest"),
    ]
    assert job_args(["--logdir", "runs/a"])[1:3] == ["--logdir", "runs/a"]


def test_cluster_config_mounts_the_repository_and_installs_the_lock_file():
    config = yaml.safe_load((ROOT / "cluster" / "cluster.yaml").read_text())
    assert config["provider"]["type"] == "local" and config["file_mounts"]["~/rllock"] == "."
    assert any("requirements.lock" in c for c in config["setup_commands"])


@pytest.mark.slow
def test_training_on_a_ray_head_started_on_loopback(tmp_path):
    port = _free_port()
    # Ray's socket paths must stay under 108 bytes: pytest's tmp_path is too deep for them.
    ray_tmp = tempfile.mkdtemp(prefix="rl", dir="/tmp")
    # Token authentication, as Ray enables it by default, with a token the head and the job share.
    env = os.environ | {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": secrets.token_hex(32), "RAY_ADDRESS": ""}
    ray_bin = shutil.which("ray", path=str(Path(sys.executable).parent)) or "ray"
    head = subprocess.Popen(
        [
            ray_bin,
            "start",
            "--head",
            "--node-ip-address=127.0.0.1",
            f"--port={port}",
            "--num-cpus=2",
            "--include-dashboard=false",
            "--disable-usage-stats",
            "--block",
            f"--temp-dir={ray_tmp}",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
        env=env,
    )
    try:
        time.sleep(8)
        assert head.poll() is None, head.stdout.read()
        logdir = tmp_path / "run"
        job = subprocess.run(
            [
                sys.executable,
                str(ROOT / "cluster" / "train_job.py"),
                *TINY,
                "--minutes",
                "4",
                "--max-learner-steps",
                "20",
                "--logdir",
                str(logdir),
                "--address",
                f"127.0.0.1:{port}",
            ],
            capture_output=True,
            text=True,
            timeout=400,
            env=env,
        )
        assert job.returncode == 0, job.stdout + job.stderr
        assert "train:" in job.stdout
        assert any(p.name.isdigit() for p in (logdir / "checkpoints").iterdir())
        assert any(p.name.isdigit() for p in (logdir / "best").iterdir())
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(head.pid, signal.SIGTERM)  # `ray start --block` stops the head's processes on exit
        try:
            head.wait(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(head.pid, signal.SIGKILL)
        shutil.rmtree(ray_tmp, ignore_errors=True)
