"""The cluster entry point's arguments and the cluster file (a run on a real multi-node cluster through
Ray Jobs: tests/test_multinode.py)."""

from __future__ import annotations

from pathlib import Path

import yaml

from cluster.train_job import job_args

ROOT = Path(__file__).resolve().parents[1]


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
