"""The trainer under faults and at the end of its budget, run as a user would: the `rllock train` command in
a subprocess."""

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

from rllock.config import MCTSConfig
from rllock.files.checkpoint import saved_steps

pytestmark = [pytest.mark.slow, pytest.mark.ray]
TINY = tiny_flags()


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


def _wait_for(
    predicate, timeout: float, proc: subprocess.Popen | None = None, lines: list | None = None
) -> None:
    """Wait for `predicate`; fail at once, with the run's output, if the run `proc` ended first."""
    end = time.monotonic() + timeout
    while not predicate():
        output = "".join(lines or [])
        assert proc is None or proc.poll() is None, f"the run ended (exit {proc.returncode}):\n{output}"
        assert time.monotonic() < end, f"timed out:\n{output}"
        time.sleep(1)


def test_sigkill_then_resume_falls_back_past_a_corrupted_checkpoint_and_sigterm_stops_it(tmp_path):
    """A run killed outright resumes from the newest checkpoint it can read; `kill`, `ray job stop` and
    schedulers send SIGTERM, which stops the resumed run like Ctrl-C: a checkpoint at the signal, the
    resume command, exit status 128 + 15."""
    logdir = tmp_path / "run"
    proc = _train(*TINY, "--minutes", "5", "--logdir", str(logdir))
    try:
        _wait_for(lambda: len([s for s in _steps(logdir) if s > 0]) >= 2, timeout=240)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the driver and everything it started, mid-run
        proc.wait()
    killed_at = _steps(logdir)
    assert (logdir / "replay.npz").exists()
    # Damage the newest checkpoint's array data: the resume must fall back to the one before it.
    newest = logdir / "checkpoints" / str(killed_at[-1])
    for f in (newest / "state").rglob("*"):
        if f.is_file() and f.parent.name == "d":
            f.write_bytes(b"\0" * 9)
    proc = _train("--resume", str(logdir), "--minutes", "5")
    try:
        # SIGTERM once the step counter went on past the kill.
        _wait_for(lambda: _steps(logdir)[-1] > killed_at[-1], timeout=240, proc=proc)
        os.kill(proc.pid, signal.SIGTERM)
        out, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 143, out
    assert "falling back" in out and f"resuming {logdir} at learner step {killed_at[-2]}" in out
    assert "SIGTERM: saving a checkpoint" in out and "stopped by SIGTERM at learner step" in out
    assert f"rllock train --resume {logdir}" in out and "Traceback" not in out
    after = _steps(logdir)
    assert after[-1] > killed_at[-1] >= killed_at[-2] > 0  # the step counter goes on
    events = EventAccumulator(str(logdir))
    events.Reload()
    steps = [e.step for e in events.Scalars("charts/episodes_per_sec")]
    assert steps == sorted(steps) and steps[-1] > killed_at[-2]  # TensorBoard steps continue, no fork
    episodes = [e.value for e in events.Scalars("charts/episodes_per_sec")]
    assert all(v > 0 for v in episodes[1:])


RESTARTED = re.compile(r"self-play actor \d+ restarted \(pid \d+ -> \d+\)")


def test_a_killed_actor_is_restarted_and_ctrl_c_then_saves_a_checkpoint_and_says_how_to_resume(tmp_path):
    logdir = tmp_path / "run"
    started = time.time()
    # Ctrl-C ends the run, not its budget: with 5 minutes, a loaded machine (a fresh clone compiles every
    # numba and XLA program cold, beside the other test worker) could spend the budget on the two waits
    # below, and the run ended before the restarted actor's first batch came back.
    proc = _train(*TINY, "--minutes", "30", "--logdir", str(logdir))
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")), daemon=True)
    reader.start()

    def actor_processes():
        found = []
        for p in psutil.process_iter(["cmdline", "create_time"]):
            cmd = " ".join(p.info["cmdline"] or [])
            if "SelfPlayActor" in cmd and p.info["create_time"] >= started:
                found.append(p)
        return found

    try:
        _wait_for(lambda: actor_processes() and _steps(logdir), timeout=240, proc=proc, lines=lines)
        # Every process of the run that names the actor: the first of them was not always the actor's
        # worker (a run then went on untouched and the test timed out on the restart line).
        killed = actor_processes()
        for p in killed:
            p.kill()
        lines.append(f"[test] killed {[p.pid for p in killed]}\n")
        # The pool notices the new process when it returns its first batch; then Ctrl-C stops the run.
        _wait_for(lambda: any(RESTARTED.search(line) for line in lines), timeout=240, proc=proc, lines=lines)
        before = _steps(logdir)[-1]
        os.kill(proc.pid, signal.SIGINT)  # the driver only, as a terminal's Ctrl-C reaches it
        proc.wait(timeout=120)
        reader.join(timeout=30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    out = "".join(lines)
    assert proc.returncode == 130, out
    assert RESTARTED.search(out) and "train: stopped at learner step" in out
    assert f"rllock train --resume {logdir}" in out and "Traceback" not in out
    assert _steps(logdir)[-1] >= before and (logdir / "replay.npz").exists()


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


def test_minutes_are_a_hard_budget_even_when_a_validation_would_overrun_and_the_run_is_quiet(tmp_path):
    """Slow validations (many episodes, many simulations) must be skipped, not run past the budget. The
    run, ended by its budget with self-play batches in flight, is quiet: stderr holds the trainer's own
    INFO lines and nothing else, no warnings from Ray or JAX that the run is fine without."""
    logdir = tmp_path / "run"
    # The address file a `ray start` (or a test's Cluster) leaves behind, here of a cluster long gone: a
    # run without --address starts its own Ray instead of joining it. A short folder: Ray's socket paths
    # under it must stay within the 107 characters a Unix socket allows.
    ray_tmp = tempfile.mkdtemp(prefix="rq", dir="/tmp")
    os.makedirs(f"{ray_tmp}/ray")
    with open(f"{ray_tmp}/ray/ray_current_cluster", "w") as f:
        f.write("127.0.0.1:9")
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"} | {"RAY_TMPDIR": ray_tmp}
    # Slow on any machine: a few hundred episodes would fit the budget on a fast core.
    slow = tiny_flags(
        validation_episodes=100_000,
        mcts=MCTSConfig(simulations=32, max_considered=4, raw_samples=256, candidates=8),
    )
    # Long enough for the first learner steps on a slow CI machine, Ray's start included.
    minutes = 1.5
    started = time.monotonic()
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "rllock.orchestration.cli", "train", *slow, "--minutes", str(minutes)]
            + ["--logdir", str(logdir)],
            capture_output=True,
            text=True,
            timeout=300,
            env=env,
        )
    finally:
        shutil.rmtree(ray_tmp, ignore_errors=True)
    elapsed = time.monotonic() - started
    assert proc.returncode == 0, proc.stderr
    assert elapsed <= minutes * 60 + 30, elapsed
    assert "validation skipped" in proc.stderr and _steps(logdir) and _steps(logdir)[-1] > 0
    assert proc.stdout.startswith("train: ") and f"{_steps(logdir)[-1]} learner steps" in proc.stdout
    for needle in NOISE:
        assert needle not in proc.stderr, f"{needle!r} in:\n{proc.stderr}"
    lines = proc.stderr.strip().splitlines()
    assert lines and all(OUR_LINE.match(line) for line in lines), proc.stderr
    assert "tensorboard" not in proc.stdout  # the one next step is the demo's last line, not one per command
