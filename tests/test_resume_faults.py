"""The trainer under faults and at the end of its budget, run as a user would: the `rllock train` command in
a subprocess. One run meets every fault in turn (Ray's start, the actors' compilation and the learner's are
paid once): a killed actor, then the whole run killed outright; its resume meets a corrupted checkpoint
and ends on its budget."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import psutil
import pytest
from helpers import tiny_flags
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from rllock.files.checkpoint import saved_steps

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
OUR_LINE = re.compile(
    r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d+ (INFO|WARNING) (orchestration|learner|actors|rllock)\."
)


def _train(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "rllock.orchestration.cli", "train", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )


def _steps(logdir: Path) -> list[int]:
    return saved_steps(logdir / "checkpoints")


def _wait_for(predicate, timeout: float, proc: subprocess.Popen, lines: list) -> None:
    """Wait for `predicate`; fail at once, with the run's output, if the run `proc` ended first."""
    end = time.monotonic() + timeout
    while not predicate():
        output = "".join(lines)
        assert proc.poll() is None, f"the run ended (exit {proc.returncode}):\n{output}"
        assert time.monotonic() < end, f"timed out:\n{output}"
        time.sleep(0.5)


RESTARTED = re.compile(r"self-play actor \d+ restarted \(pid \d+ -> \d+\)")


def _actor_processes(since: float) -> list[psutil.Process]:
    found = []
    for p in psutil.process_iter(["cmdline", "create_time"]):
        cmd = " ".join(p.info["cmdline"] or [])
        if "SelfPlayActor" in cmd and p.info["create_time"] >= since:
            found.append(p)
    return found


def test_a_killed_actor_restarts_a_killed_run_resumes_past_a_corrupted_checkpoint_and_ends_quietly(tmp_path):
    """A self-play actor killed mid-run is restarted and the run goes on. A run killed outright resumes
    from the newest checkpoint it can read. The resumed run's minutes are a hard budget: slow validations
    (many episodes) are skipped, not run past it, and the run, ended by its budget with self-play
    batches in flight, is quiet: stderr holds the trainer's own log lines and nothing else, no warnings
    from Ray or JAX that the run is fine without. (A signal's checkpoint and resume command are tested
    by `ray job stop` in test_multinode.py and by test_guide.py's SIGTERM to `train-guide`.)"""
    logdir = tmp_path / "run"
    started = time.time()
    # Slow on any machine: a few hundred episodes would fit the budget on a fast core.
    slow = tiny_flags(validation_episodes=100_000)
    proc = _train(*slow, "--minutes", "5", "--logdir", str(logdir))
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")), daemon=True)
    reader.start()
    try:
        _wait_for(lambda: _actor_processes(started) and _steps(logdir), 240, proc, lines)
        # Every process of the run that names the actor: the first of them was not always the actor's
        # worker (a run then went on untouched and the test timed out on the restart line).
        killed = _actor_processes(started)
        for p in killed:
            p.kill()
        lines.append(f"[test] killed {[p.pid for p in killed]}\n")
        # The pool notices the new process when it returns its first batch.
        _wait_for(lambda: any(RESTARTED.search(line) for line in lines), 240, proc, lines)
        restarted = _steps(logdir)[-1]
        _wait_for(lambda: len([s for s in _steps(logdir) if s > restarted]) >= 2, 240, proc, lines)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the driver and everything it started, mid-run
        proc.wait()
        reader.join(timeout=30)
    killed_at = _steps(logdir)
    assert (logdir / "replay.npz").exists()
    # Damage the newest checkpoint's array data: the resume must fall back to the one before it.
    newest = logdir / "checkpoints" / str(killed_at[-1])
    for f in (newest / "state").rglob("*"):
        if f.is_file() and f.parent.name == "d":
            f.write_bytes(b"\0" * 9)
    # The address file a `ray start` (or a test's Cluster) leaves behind, here of a cluster long gone: a
    # run without --address starts its own Ray instead of joining it. A short folder: Ray's socket paths
    # under it must stay within the 107 characters a Unix socket allows.
    ray_tmp = tempfile.mkdtemp(prefix="rq", dir="/tmp")
    os.makedirs(f"{ray_tmp}/ray")
    with open(f"{ray_tmp}/ray/ray_current_cluster", "w") as f:
        f.write("127.0.0.1:9")
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"} | {"RAY_TMPDIR": ray_tmp}
    # Long enough for learner steps on a slow CI machine, Ray's start and the actor's compilation
    # included (the learner waits for new episodes).
    minutes = 0.75
    began = time.monotonic()
    try:
        done = subprocess.run(
            [sys.executable, "-m", "rllock.orchestration.cli", "train", "--resume", str(logdir)]
            + ["--minutes", str(minutes)],
            capture_output=True,
            text=True,
            timeout=300,
            env=env,
        )
    finally:
        shutil.rmtree(ray_tmp, ignore_errors=True)
    elapsed = time.monotonic() - began
    out, err = done.stdout, done.stderr
    assert done.returncode == 0, err
    assert elapsed <= minutes * 60 + 30, (elapsed, err)
    assert "falling back" in err and f"resuming {logdir} at learner step {killed_at[-2]}" in err
    assert "validation skipped" in err
    # The step counter goes on from the checkpoint it resumed at, and the run's last step is saved.
    final = re.match(r"train: (\d+) learner steps", out)
    assert final and int(final[1]) > killed_at[-2] > 0 and int(final[1]) in _steps(logdir), (out, err)
    for needle in NOISE:
        assert needle not in err, f"{needle!r} in:\n{err}"
    lines = err.strip().splitlines()
    assert lines and all(OUR_LINE.match(line) for line in lines), err
    assert "tensorboard" not in out  # the one next step is the demo's last line, not one per command
    events = EventAccumulator(str(logdir))
    events.Reload()
    steps = [e.step for e in events.Scalars("charts/episodes_per_sec")]
    assert steps == sorted(steps) and steps[-1] > killed_at[-2]  # TensorBoard steps continue, no fork
    episodes = [e.value for e in events.Scalars("charts/episodes_per_sec")]
    assert all(v > 0 for v in episodes[1:])
