"""Training on a real multi-node Ray cluster on this machine, submitted through Ray Jobs: a head (no
CPUs, the Jobs API) and two worker nodes of one CPU each, every node with its own raylet, all on
127.0.0.1 (`ray.cluster_utils.Cluster`; with RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0 Ray keeps loopback
addresses). The same cluster first runs `solve --address`. A worker node is killed mid-run, a new one
joins, and `ray job stop` ends the run."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from helpers import actor_nodes, run_cli, tiny_flags

from rllock.config import SelfPlayConfig
from rllock.core.verifier import verify_labels
from rllock.files.assembly import read_assembly
from rllock.files.checkpoint import saved_steps
from rllock.search.portfolio import worker_seed

ROOT = Path(__file__).resolve().parents[1]
RAY = shutil.which("ray", path=str(Path(sys.executable).parent)) or "ray"


def _latest(logdir: Path) -> int:
    """The newest saved learner step, -1 before the first."""
    return max(saved_steps(logdir / "checkpoints"), default=-1)


def _wait_for(what: str, condition: Callable[[], object], timeout: float, logs: Callable[[], str]):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if value := condition():
            return value
        time.sleep(0.5)
    pytest.fail(f"timed out waiting for {what}; the job's log:\n{logs()[-6000:]}")


def _run(command: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=120)


@pytest.mark.slow
@pytest.mark.ray
def test_a_multinode_cluster_solves_then_trains_through_a_lost_node_until_ray_job_stop(cluster, tmp_path):
    from ray.job_submission import JobStatus, JobSubmissionClient

    ray_cluster, api, add_worker = cluster
    workers = [add_worker() for _ in range(2)]
    ray_cluster.wait_for_nodes()
    nodes = [ray_cluster.head_node, *workers]
    assert {n.node_ip_address for n in nodes} == {"127.0.0.1"}  # loopback only

    # `solve --address` on the same cluster first: its workers are Ray actors, one on each worker node;
    # the assemblies are verified and written, and no worker is left alive for the training after it.
    out = tmp_path / "solved"
    code, stdout, err = run_cli(
        "solve", "--shape", "cube4", "--pieces", "7", "--count", "2", "--workers", "2",
        "--address", ray_cluster.address, "--out", str(out),
    )  # fmt: skip
    assert code == 0 and "solve: 2 valid assemblies" in stdout, err
    line = next(x for x in err.splitlines() if "search workers on" in x)
    assert "on 2 Ray node(s)" in line and all(w.node_id in line for w in workers), line
    for folder in sorted(out.glob("assembly_*")):
        labels, meta = read_assembly(folder)
        assert verify_labels(labels).valid
        method = json.loads((folder / "assembly.json").read_text())["method"]
        assert method["workers"] == 2 and method["ray"] is True
        assert meta["seed"] in {worker_seed(0, 0), worker_seed(0, 1)}
    assert not actor_nodes(api, "_RayWorker")

    logdir = tmp_path / "run"
    job = "rllock-multinode-" + tmp_path.name[-8:]
    command = [RAY, "job", "submit", "--address", api, "--working-dir", ".", "--submission-id", job]
    # Validations and a learner stepping flat out would take the cores the actors need here.
    flags = tiny_flags(
        selfplay=SelfPlayConfig(actors=2, episodes_per_batch=4), validate_minutes=10.0, replay_ratio=0.25
    )
    train = [sys.executable, "cluster/train_job.py", *flags, "--minutes", "20", "--logdir", str(logdir)]
    # A head node under load may not have its job agent up yet (30 s were not enough beside the other
    # pytest worker on a slow VM); Ray's own words say to retry.
    agent_deadline = time.monotonic() + 180
    while True:
        submitted = subprocess.run(
            [*command, "--no-wait", "--", *train], cwd=ROOT, capture_output=True, text=True
        )
        if (
            submitted.returncode == 0
            or "No available agent to submit job" not in submitted.stderr
            or time.monotonic() > agent_deadline
        ):
            break
        time.sleep(3)
    assert submitted.returncode == 0, submitted.stdout + submitted.stderr
    client = JobSubmissionClient(api)

    def logs() -> str:
        return subprocess.run(
            [RAY, "job", "logs", "--address", api, job], capture_output=True, text=True
        ).stdout

    # Placement: an actor on each worker node, the replay buffer on the driver's node.
    worker_ids = {w.node_id for w in workers}
    _wait_for("a self-play actor on each worker node", lambda: actor_nodes(api) == worker_ids, 120, logs)
    driver = client.get_job_info(job).driver_node_id
    assert driver == ray_cluster.head_node.node_id
    # The state API lists an actor once its process is up, which on 2 busy cores may come after the workers'.
    _wait_for(
        "the replay buffer on the driver's node",
        lambda: actor_nodes(api, "ReplayBuffer") == {driver},
        60,
        logs,
    )
    # The actors' first episodes wait for their compiled search: on a slow, busy machine (a 2-core VM
    # while the other test worker compiles too) that took more than 100 s, and on a fresh CI machine more
    # than 240 s, when the job's uploaded copy of the repository compiled the search anew on each node.
    # It now loads the install's compiled code (`rllock.core.numba_cache`); the wait stays generous.
    _wait_for("a learner step", lambda: _latest(logdir) >= 0, 600, logs)

    # A worker node dies (SIGKILL to its processes): the learner keeps stepping on the other.
    ray_cluster.remove_node(workers[1], allow_graceful=False)
    lost = f"node {workers[1].node_id[:8]} (127.0.0.1) was lost"
    _wait_for("the run to notice the lost node", lambda: lost in logs(), 90, logs)
    noticed = _latest(logdir)
    _wait_for("learner steps after the node loss", lambda: _latest(logdir) >= noticed + 5, 90, logs)

    # A node joins: the actor that lost its node restarts there.
    joined = add_worker()
    _wait_for("the actor restarted on the new node", lambda: joined.node_id in actor_nodes(api), 60, logs)

    # `ray job stop`: SIGTERM, a checkpoint at the signal, the resume command.
    before = _latest(logdir)
    stopped = _run([RAY, "job", "stop", "--address", api, job])
    assert stopped.returncode == 0, stopped.stdout + stopped.stderr
    assert client.get_job_status(job) == JobStatus.STOPPED
    text = logs()
    assert "SIGTERM: saving a checkpoint" in text and "Traceback" not in text
    step = int(text.split("stopped by SIGTERM at learner step ")[1].split(";")[0])
    assert step >= before and _latest(logdir) == step
    # The command's last words, as a terminal's Ctrl-C gets them too (the same stop, tests/test_stopping.py)
    assert f"train: stopped at learner step {step}; resume with: rllock train --resume {logdir}" in text
    assert (logdir / "replay.npz").exists() and list(logdir.glob("events.out.tfevents.*"))
