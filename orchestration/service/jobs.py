"""Jobs of `rllock serve`: their records on disk, and the queue that runs at most `max_jobs` of them at
once.

A job lives in DATA/jobs/<id>/: job.json (its request, state and result, replaced atomically on every
change), shape.npy (the voxel grid, so that a queued job can run after a restart), and once done the
files of its assemblies, assembly_001/ (assembly.json, assembly.puz, assembly.png), each verified by
the full verifier before it is written.

The queue knows nothing of Ray: it starts, waits for, collects and cancels jobs through a `Runner`
(`work.RayRunner` in the server), so that its rules hold the same for any runner and can be checked
without a cluster. Its pump, a thread, starts queued jobs as slots free and collects finished ones.
"""

from __future__ import annotations

import json
import logging
import os
import re
import threading
import time
import uuid
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from rllock.orchestration.service.request import JobSpec, spec_from_json, spec_json

FINAL = frozenset({"done", "failed", "cancelled"})
STATES = frozenset({"queued", "running"}) | FINAL
JOB_ID = re.compile(r"^[0-9a-f]{12}$")
ASSEMBLY = "assembly_001"
"""The folder of a done job's assembly (the service asks for one)."""
ASSEMBLY_FILES: Mapping[str, str] = {
    "assembly.json": "application/json",
    "assembly.puz": "text/plain",
    "assembly.png": "image/png",
}
"""The files of a done job's assembly that the API serves, with their media types."""
PUMP_WAIT_S = 0.2

# In the replicas, Ray Serve's logger is the one with handlers (its log files, and the server's stderr).
log = logging.getLogger("ray.serve.rllock")


class NoSuchJob(LookupError):
    """No job has this id."""


class WrongState(Exception):
    """The job's state does not allow what was asked (cancel an ended job, files of an unfinished one)."""


class TooManyJobs(Exception):
    """The client already has as many queued and running jobs as the server allows."""


class JobFailed(Exception):
    """A job's run ended without its files; the message is the record's one-line error, and `offer` (a
    solve job's) the nearest task that works, kept in the record's result."""

    def __init__(self, message: str, offer: dict | None = None):
        super().__init__(message)
        self.offer = offer


# --- records -----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class JobRecord:
    """A job's request, state and result: what job.json holds. A change of state is a new record
    (`moved`), written whole, so that a reader never sees half of one."""

    id: str
    client: str
    spec: JobSpec
    n: int  # voxels of the shape: "N" in job.json and the API
    created: float
    state: str = "queued"
    started: float | None = None
    finished: float | None = None
    error: str | None = None
    result: dict | None = None

    def to_json(self) -> dict:
        """job.json's document, its keys in the order the server has always written them."""
        return {
            "id": self.id,
            "client": self.client,
            "spec": spec_json(self.spec),
            "N": self.n,
            "state": self.state,
            "created": self.created,
            "started": self.started,
            "finished": self.finished,
            "error": self.error,
            "result": self.result,
        }

    @classmethod
    def from_json(cls, doc: object) -> JobRecord:
        """The record of a job.json document; ValueError for one that is not a job's."""
        if not isinstance(doc, dict) or not JOB_ID.match(str(doc.get("id", ""))):
            raise ValueError("not a job record: no job id")
        if doc.get("state") not in STATES or not isinstance(doc.get("spec"), dict):
            raise ValueError(f"job {doc['id']}: no state or request")
        try:
            return cls(
                id=doc["id"],
                client=str(doc.get("client", "unknown")),
                spec=spec_from_json(doc["spec"]),
                n=int(doc["N"]),
                created=float(doc["created"]),
                state=doc["state"],
                started=doc.get("started"),
                finished=doc.get("finished"),
                error=doc.get("error"),
                result=doc.get("result"),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"job {doc['id']}: {exc}") from None


def new_record(client: str, spec: JobSpec, n: int, now: float) -> JobRecord:
    """A queued job with a fresh id."""
    return JobRecord(id=uuid.uuid4().hex[:12], client=client, spec=spec, n=n, created=now)


def moved(
    record: JobRecord, state: str, now: float, *, error: str | None = None, result: dict | None = None
) -> JobRecord:
    """The record in `state`: running stamps `started`; an end stamps `finished` with its error or
    result; queued again (a restart) forgets when it started."""
    if state == "queued":
        return replace(record, state=state, started=None)
    if state == "running":
        return replace(record, state=state, started=now)
    assert state in FINAL, state
    return replace(record, state=state, finished=now, error=error, result=result)


def job_view(record: JobRecord, progress: dict | None, position: int | None) -> dict:
    """What the API says of a job: its record but the client's address, its latest progress, its place
    in the queue while queued, and the addresses of its files once done."""
    view = record.to_json()
    del view["client"]
    view["progress"] = progress
    if record.state == "queued":
        view["queue_position"] = position
    if record.state == "done":
        base = f"/api/jobs/{record.id}"
        view["files"] = {name: f"{base}/files/{name}" for name in ASSEMBLY_FILES} | {
            "pieces.zip": f"{base}/pieces.zip"
        }
    return view


def write_json(path: Path, doc: dict) -> None:
    """`doc` written to `path` whole or not at all (a crash never leaves half a record)."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(doc, indent=1))
    os.replace(tmp, path)


def read_records(jobs: Path) -> list[JobRecord]:
    """Every readable job record under `jobs`, oldest first. A job the server was running or holding in
    its queue when it stopped is queued again: its request and shape are on disk."""
    records = []
    for path in sorted(jobs.glob("*/job.json")):
        try:
            record = JobRecord.from_json(json.loads(path.read_text()))
        except (OSError, ValueError):  # json's decode error is a ValueError too
            continue
        records.append(record if record.state in FINAL else moved(record, "queued", 0.0))
    return sorted(records, key=lambda r: r.created)


def write_files(folder: Path, files: Mapping[str, bytes]) -> None:
    """A finished job's files (by path relative to its folder) into its folder."""
    for name, data in files.items():
        path = folder / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)


def count_states(records: list[JobRecord]) -> dict[str, int]:
    states: dict[str, int] = {}
    for record in records:
        states[record.state] = states.get(record.state, 0) + 1
    return states


# --- the queue ---------------------------------------------------------------------------------------


class Runner(Protocol):
    """Where jobs run. A handle is whatever `start` returns; `result` raises `JobFailed` for a job that
    failed or whose worker died."""

    def start(self, job_id: str, spec: JobSpec, grid: np.ndarray) -> Any: ...

    def ready(self, handles: list[Any], timeout: float) -> list[Any]: ...

    def result(self, handle: Any) -> tuple[dict, dict[str, bytes]]: ...

    def cancel(self, handle: Any) -> None: ...


class JobQueue:
    """The jobs on record, the queue, and those running. Every change happens under one lock and is
    written to job.json before the lock is let go, so that the API and the disk agree."""

    def __init__(self, folder: Path, runner: Runner, max_jobs: int) -> None:
        self.folder = folder
        self.runner = runner
        self.max_jobs = max_jobs
        folder.mkdir(parents=True, exist_ok=True)
        self._lock = threading.RLock()
        records = read_records(folder)
        self._records = {r.id: r for r in records}
        self._queue = deque(r.id for r in records if r.state == "queued")
        for job_id in self._queue:  # a job that was running when the server stopped: queued on disk too
            write_json(folder / job_id / "job.json", self._records[job_id].to_json())
        self._running: dict[str, Any] = {}
        self._progress: dict[str, dict] = {}

    # -- the pump --

    def start_pump(self) -> threading.Thread:
        """The thread that runs the queue for as long as the process lives."""
        thread = threading.Thread(target=self._pump, name="job-queue", daemon=True)
        thread.start()
        return thread

    def _pump(self) -> None:
        while True:
            try:
                self.pump_once()
            except Exception:  # the queue must outlive any one job's trouble; the log says what it was
                log.exception("the job queue's pump")
                time.sleep(1.0)

    def pump_once(self, wait_s: float = PUMP_WAIT_S) -> None:
        """One turn: collect the jobs that finished within `wait_s`, then start queued ones while slots
        are free."""
        with self._lock:
            handles = list(self._running.values())
        if handles:
            ready = self.runner.ready(handles, wait_s)
        else:
            time.sleep(wait_s)
            ready = []
        for handle in ready:
            self._collect(handle)
        with self._lock:
            while self._queue and len(self._running) < self.max_jobs:
                self._start(self._queue.popleft())

    def _start(self, job_id: str) -> None:
        record = self._records[job_id]
        try:
            grid = np.load(self.folder / job_id / "shape.npy")
        except (OSError, ValueError) as exc:
            self._set(moved(record, "failed", time.time(), error=f"its shape is unreadable: {exc}"))
            return
        self._running[job_id] = self.runner.start(job_id, record.spec, grid)
        self._set(moved(record, "running", time.time()))

    def _collect(self, handle: Any) -> None:
        with self._lock:
            job_id = next((j for j, h in self._running.items() if h == handle), None)
        if job_id is None:  # cancelled meanwhile
            return
        try:
            summary, files = self.runner.result(handle)
        except JobFailed as exc:
            with self._lock:
                if self._running.pop(job_id, None) is not None:
                    offer = None if exc.offer is None else {"offer": exc.offer}
                    record = self._records[job_id]
                    self._set(moved(record, "failed", time.time(), error=str(exc), result=offer))
            return
        write_files(self.folder / job_id, files)
        with self._lock:
            if self._running.pop(job_id, None) is not None:
                self._set(moved(self._records[job_id], "done", time.time(), result=summary))

    def _set(self, record: JobRecord) -> None:
        """`record` becomes the job's record, on disk as in memory."""
        before = self._records.get(record.id)
        self._records[record.id] = record
        if before is None or before.state != record.state:
            spec = record.spec
            log.info(
                "job %s (%s %s K=%s): %s%s",
                record.id,
                spec.method,
                spec.shape,
                "auto" if spec.pieces is None else spec.pieces,
                record.state,
                f": {record.error}" if record.error else "",
            )
        if record.state in FINAL:
            self._progress.pop(record.id, None)
        write_json(self.folder / record.id / "job.json", record.to_json())

    # -- what the API asks --

    def check_client(self, client: str, max_client_jobs: int) -> None:
        """TooManyJobs when `client` has `max_client_jobs` jobs queued or running."""
        with self._lock:
            active = sum(1 for r in self._records.values() if r.client == client and r.state not in FINAL)
        if active >= max_client_jobs:
            raise TooManyJobs(
                f"you have {active} jobs queued or running, the server's limit: wait for one to finish"
            )

    def submit(self, client: str, spec: JobSpec, grid: np.ndarray, max_client_jobs: int) -> dict:
        """A new queued job's view; its folder, shape and record are on disk before it is queued."""
        with self._lock:
            self.check_client(client, max_client_jobs)
            record = new_record(client, spec, int(grid.sum()), time.time())
            folder = self.folder / record.id
            folder.mkdir()
            np.save(folder / "shape.npy", grid)
            self._set(record)
            self._queue.append(record.id)
            return self._view(record)

    def cancel(self, job_id: str) -> dict:
        """Stop a queued or running job; WrongState for one that has ended."""
        with self._lock:
            record = self.record(job_id)
            if record.state in FINAL:
                raise WrongState(f"job {job_id} has already ended ({record.state})")
            if job_id in self._queue:
                self._queue.remove(job_id)
            handle = self._running.pop(job_id, None)
            if handle is not None:
                self.runner.cancel(handle)
            self._set(moved(record, "cancelled", time.time()))
            return self._view(self._records[job_id])

    def progress(self, job_id: str, progress: dict) -> None:
        """A running job's latest progress (sent by its run)."""
        with self._lock:
            if job_id in self._running:
                self._progress[job_id] = progress

    def record(self, job_id: str) -> JobRecord:
        with self._lock:
            if not JOB_ID.match(job_id) or job_id not in self._records:
                raise NoSuchJob(f"no job {job_id[:40]!r}")
            return self._records[job_id]

    def assembly(self, job_id: str) -> Path:
        """The folder of a done job's assembly; WrongState before it is done."""
        record = self.record(job_id)
        if record.state != "done":
            raise WrongState(f"job {job_id} has no files: it is {record.state}")
        return self.folder / job_id / ASSEMBLY

    def view(self, job_id: str) -> dict:
        with self._lock:
            return self._view(self.record(job_id))

    def views(self) -> list[dict]:
        """Every job's view, newest first."""
        with self._lock:
            return [self._view(r) for r in sorted(self._records.values(), key=lambda r: -r.created)]

    def counts(self) -> dict[str, int]:
        """Jobs on record by state."""
        with self._lock:
            return count_states(list(self._records.values()))

    def _view(self, record: JobRecord) -> dict:
        position = self._queue.index(record.id) + 1 if record.id in self._queue else None
        return job_view(record, self._progress.get(record.id), position)
