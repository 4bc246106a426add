"""`rllock bench serve`: a load test of `rllock serve` on loopback. The same generate jobs (seeds 0..J-1)
submitted all at once, then one after another, to one server; every result verified; the mean number of
requests and states per network call of the model deployment, throughput, and p50/p95 time to result.

`ServerProcess` runs `rllock serve` in a process of its own (also for the tests).
"""

from __future__ import annotations

import logging
import os
import random
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import requests

from rllock.core.verifier import verify_labels
from rllock.errors import RLLockError

log = logging.getLogger(__name__)
FINAL = ("done", "failed", "cancelled")


def free_port() -> int:
    """A loopback port free now, below the range the OS hands out to port-0 binds and outgoing
    connections: a port from that range (as binding port 0 gives) was taken by one of Ray's own
    processes, which bind port 0, before the server bound it ("Failed to bind", seen under load)."""
    low = _ephemeral_low()
    low = low if low > 10_000 else 32768
    draw = random.SystemRandom()
    for _ in range(100):
        port = draw.randrange(10_000, low)
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise RLLockError(f"no free loopback port found between 10000 and {low}")


def _ephemeral_low() -> int:
    """The low end of Linux's ephemeral port range (32768 where it cannot be read)."""
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


class ServerProcess:
    """`rllock serve` on a free loopback port with the data folder `data` (which outlives the process, so
    a second `start` is a restart), and a small client of its API."""

    def __init__(self, data: Path, args: list[str] | None = None, log_path: Path | None = None):
        self.data, self.port, self.args = data, free_port(), args or []
        self.url = f"http://127.0.0.1:{self.port}"
        self.log_path = log_path or data.parent / "serve.log"
        self.proc: subprocess.Popen | None = None

    def start(self, timeout: float = 180.0) -> float:
        """Start the server; the seconds until /api/health answered."""
        began = time.monotonic()
        command = [sys.executable, "-m", "rllock.orchestration.cli", "serve", "--port", str(self.port)]
        with open(self.log_path, "a") as out:
            self.proc = subprocess.Popen(
                [*command, "--data", str(self.data), *self.args],
                stdout=out,
                stderr=subprocess.STDOUT,
                env={**os.environ, "RAY_ADDRESS": ""},
                start_new_session=True,  # its Ray processes with it, so that a kill reaches them all
            )
        try:
            while time.monotonic() - began < timeout:
                if self.proc.poll() is not None:
                    raise RLLockError(f"the server exited: {self.log_path.read_text()[-2000:]}")
                try:
                    if requests.get(f"{self.url}/api/health", timeout=10).ok:
                        return time.monotonic() - began
                except requests.RequestException:  # not listening yet, or the proxy before the application
                    pass
                time.sleep(0.2)
            raise RLLockError(f"the server did not answer within {timeout:g} s")
        except BaseException:
            self.stop()
            raise

    def stop(self) -> int:
        """SIGTERM, as Ctrl-C would; the exit status. After 60 s, or if the server is gone, its whole
        process group is killed: no Ray process of it outlives this call."""
        if self.proc is None:
            return 0
        status = self.proc.poll()
        if status is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                status = self.proc.wait(60)
            except subprocess.TimeoutExpired:
                status = None
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        return self.proc.wait() if status is None else status

    def get(self, path: str, **kw) -> requests.Response:
        return requests.get(self.url + path, timeout=60, **kw)

    def post(self, path: str, **kw) -> requests.Response:
        return requests.post(self.url + path, timeout=120, **kw)

    def job(self, files=None, **fields) -> dict:
        r = self.post("/api/jobs", data={k: str(v) for k, v in fields.items()}, files=files)
        if r.status_code != 201:
            raise RLLockError(f"the server refused a job: {r.text}")
        return r.json()

    def wait(self, job_id: str, seconds: float = 120.0, until: tuple[str, ...] = FINAL) -> dict:
        end = time.monotonic() + seconds
        while True:
            view = self.get(f"/api/jobs/{job_id}").json()
            if view["state"] in until:
                return view
            if time.monotonic() > end:
                raise RLLockError(f"job {job_id} still {view['state']} after {seconds:g} s")
            time.sleep(0.2)

    def verified(self, job: dict) -> np.ndarray:
        """The labels of a done job's assembly, after the full verifier passed them here too."""
        doc = self.get(job["files"]["assembly.json"]).json()
        labels = np.asarray(doc["labels"]).reshape(doc["dimensions"][::-1]).transpose(2, 1, 0)
        if not (doc["verification"]["valid"] and verify_labels(labels, doc["removal"]).valid):
            raise RLLockError(f"job {job['id']}'s assembly does not verify")
        return labels


@dataclass(frozen=True)
class Arm:
    name: str
    jobs: int
    verified: int
    wall_s: float
    to_result_s: list[float]  # per job: from its submission to its end (the server's clock)
    calls: int
    requests: int
    states: int

    @property
    def throughput_per_min(self) -> float:
        return 60.0 * self.verified / self.wall_s

    def percentile(self, q: float) -> float:
        return float(np.percentile(self.to_result_s, q))

    def to_json(self) -> dict:
        return {
            "arm": self.name,
            "jobs": self.jobs,
            "verified": self.verified,
            "wall_s": round(self.wall_s, 2),
            "jobs_per_min": round(self.throughput_per_min, 2),
            "p50_s": round(self.percentile(50), 2),
            "p95_s": round(self.percentile(95), 2),
            "network_calls": self.calls,
            "requests_per_call": round(self.requests / max(self.calls, 1), 2),
            "states_per_call": round(self.states / max(self.calls, 1), 2),
        }


def _arm(server: ServerProcess, name: str, specs: list[dict], together: bool, limit: float) -> Arm:
    before = server.get("/api/stats").json()["model"]
    began = time.monotonic()
    if together:
        submitted = [server.job(**spec) for spec in specs]
        ended = [server.wait(job["id"], limit) for job in submitted]
    else:
        ended = [server.wait(server.job(**spec)["id"], limit) for spec in specs]
    wall = time.monotonic() - began
    after = server.get("/api/stats").json()["model"]
    done = [job for job in ended if job["state"] == "done"]
    for job in done:
        server.verified(job)
    lost = [
        f"{job['id']}: {job['state']} {job.get('error') or ''}" for job in ended if job["state"] != "done"
    ]
    if lost:
        log.warning("%s: %d jobs did not end with an assembly: %s", name, len(lost), "; ".join(lost))
    return Arm(
        name,
        len(specs),
        len(done),
        wall,
        [job["finished"] - job["created"] for job in ended],
        after["calls"] - before["calls"],
        after["requests"] - before["requests"],
        after["states"] - before["states"],
    )


def load_test(
    *, jobs: int, shape: str, pieces: int, time_limit: float, max_jobs: int
) -> tuple[list[Arm], float]:
    """(the concurrent and the one-after-another arm, the server's start-up seconds). A warm-up of
    `max_jobs` jobs first, so that neither arm pays for compiling the search in the job workers."""
    specs = [
        {"shape": shape, "pieces": pieces, "method": "generate", "seed": s, "time_limit": time_limit}
        for s in range(jobs)
    ]
    limit = time_limit * jobs + 120
    with tempfile.TemporaryDirectory(prefix="rllock-bench-serve-") as folder:
        args = ["--max-client-jobs", str(jobs), "--max-jobs", str(max_jobs)]
        server = ServerProcess(Path(folder) / "data", args)
        up = server.start()
        try:
            warm = [{**spec, "seed": 1000 + i} for i, spec in enumerate(specs[:max_jobs])]
            _arm(server, "warm-up", warm, True, limit)
            arms = [
                _arm(server, "together", specs, True, limit),
                _arm(server, "one after another", specs, False, limit),
            ]
        finally:
            server.stop()
    return arms, up


def format_load_table(arms: list[Arm], command: str, up: float) -> str:
    lines = [
        f"`{command}` (server up in {up:.1f} s)",
        "",
        "| arm | jobs | verified | wall s | jobs per min | p50 s | p95 s | network calls | requests per call "
        "| states per call |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for arm in arms:
        lines.append("| " + " | ".join(str(v) for v in arm.to_json().values()) + " |")
    if len(arms) == 2 and arms[1].throughput_per_min:
        lines.append("")
        ratio = arms[0].throughput_per_min / arms[1].throughput_per_min
        lines.append(f"throughput together / one after another: {ratio:.2f}")
    return "\n".join(lines) + "\n"
