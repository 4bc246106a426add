"""The service's parts without Ray: job records as job.json holds them (those an older server wrote
load), the queue's rules with a stand-in runner, and the HTTP routes called in-process over that queue
(the body-size guard, the one-line errors, a job from request to cancel)."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import numpy as np
import pytest

from rllock.errors import RLLockError
from rllock.orchestration.service.app import Ingress, make_api
from rllock.orchestration.service.files import check_print, declared_too_large, zip_name
from rllock.orchestration.service.jobs import (
    JobFailed,
    JobQueue,
    JobRecord,
    NoSuchJob,
    TooManyJobs,
    WrongState,
    job_view,
    read_records,
)
from rllock.orchestration.service.request import JobSpec, Limits, TooLarge, shape_grid

# job.json as the server has written it since the service began (dicts, before typed records).
OLD_RECORD = {
    "id": "0123456789ab",
    "client": "127.0.0.1",
    "spec": {
        "method": "solve",
        "shape": "cube4",
        "pieces": 6,
        "removal": "straight",
        "resolution": None,
        "time_limit": 60.0,
        "seed": 1,
        "checkpoint": None,
    },
    "N": 64,
    "state": "done",
    "created": 1700000000.5,
    "started": 1700000001.0,
    "finished": 1700000003.25,
    "error": None,
    "result": {"assemblies": 1, "seconds": 2.1, "nodes": 40},
}


class FakeRunner:
    """Jobs that finish when the test says so."""

    def __init__(self) -> None:
        self.started: list[str] = []
        self.outcomes: dict[str, object] = {}
        self.cancelled: list[str] = []

    def start(self, job_id: str, spec: JobSpec, grid: np.ndarray) -> str:
        self.started.append(job_id)
        return job_id

    def ready(self, handles: list, timeout: float) -> list:
        return [h for h in handles if h in self.outcomes]

    def result(self, handle: str) -> tuple[dict, dict[str, bytes]]:
        outcome = self.outcomes[handle]
        if isinstance(outcome, str):
            raise JobFailed(outcome)
        return outcome  # type: ignore[return-value]

    def cancel(self, handle: str) -> None:
        self.cancelled.append(handle)


def _write(folder: Path, doc: dict) -> None:
    (folder / doc["id"]).mkdir(parents=True)
    (folder / doc["id"] / "job.json").write_text(json.dumps(doc, indent=1))


def test_records_round_trip_and_old_job_files_load(tmp_path):
    record = JobRecord.from_json(OLD_RECORD)
    assert record.spec == JobSpec("solve", "cube4", 6, seed=1) and record.n == 64
    assert record.to_json() == OLD_RECORD and list(record.to_json()) == list(OLD_RECORD)
    running = {**OLD_RECORD, "id": "0123456789ac", "state": "running", "created": 1.0}
    newer = {**OLD_RECORD, "id": "0123456789ad", "spec": {**OLD_RECORD["spec"], "priority": 3}}
    _write(tmp_path, OLD_RECORD)
    _write(tmp_path, running)
    _write(tmp_path, newer)
    _write(tmp_path, {**OLD_RECORD, "id": "../etc"})  # not a job's id
    (tmp_path / "0123456789ae").mkdir()
    (tmp_path / "0123456789ae" / "job.json").write_text("{half a rec")
    records = read_records(tmp_path)
    assert [r.id for r in records] == ["0123456789ac", "0123456789ab", "0123456789ad"]  # oldest first
    assert records[0].state == "queued" and records[0].started is None  # was running: queued again
    assert records[2].spec == record.spec
    view = job_view(record, None, None)
    assert "client" not in view and view["files"]["pieces.zip"] == "/api/jobs/0123456789ab/pieces.zip"
    with pytest.raises(ValueError):
        JobRecord.from_json({**OLD_RECORD, "state": "lost"})


def _queue(tmp_path: Path, max_jobs: int = 1) -> tuple[JobQueue, FakeRunner]:
    runner = FakeRunner()
    return JobQueue(tmp_path / "jobs", runner, max_jobs), runner


def test_the_queue_runs_jobs_in_turn_and_writes_every_change(tmp_path):
    queue, runner = _queue(tmp_path)
    grid = np.ones((4, 4, 4), bool)
    a = queue.submit("1.2.3.4", JobSpec("solve", "cube4", 6), grid, 5)
    b = queue.submit("1.2.3.4", JobSpec("solve", "cube4", 7), grid, 5)
    assert (a["state"], a["queue_position"], b["queue_position"]) == ("queued", 1, 2)
    on_disk = json.loads((tmp_path / "jobs" / a["id"] / "job.json").read_text())
    assert on_disk["client"] == "1.2.3.4" and np.load(tmp_path / "jobs" / a["id"] / "shape.npy").all()
    queue.pump_once(0)
    assert runner.started == [a["id"]] and queue.view(b["id"])["queue_position"] == 1  # one slot
    queue.progress(a["id"], {"placed": 3})
    assert queue.view(a["id"])["progress"] == {"placed": 3}
    runner.outcomes[a["id"]] = ({"assemblies": 1}, {"assembly_001/assembly.puz": b"puz"})
    queue.pump_once(0)
    done = queue.view(a["id"])
    assert done["state"] == "done" and done["result"] == {"assemblies": 1} and done["progress"] is None
    assert (queue.assembly(a["id"]) / "assembly.puz").read_bytes() == b"puz"
    assert runner.started == [a["id"], b["id"]]
    runner.outcomes[b["id"]] = "no valid assembly of cube4 K=7"
    queue.pump_once(0)
    failed = json.loads((tmp_path / "jobs" / b["id"] / "job.json").read_text())
    assert failed["state"] == "failed" and failed["error"] == "no valid assembly of cube4 K=7"
    assert queue.counts() == {"done": 1, "failed": 1}
    with pytest.raises(WrongState, match="has no files: it is failed"):
        queue.assembly(b["id"])


def test_cancel_the_client_limit_and_a_restart(tmp_path):
    queue, runner = _queue(tmp_path)
    grid = np.ones((2, 2, 2), bool)
    jobs = [queue.submit("c", JobSpec("solve", "box:2x2x2", 2), grid, 3)["id"] for _ in range(3)]
    with pytest.raises(TooManyJobs, match="3 jobs queued or running"):
        queue.submit("c", JobSpec("solve", "box:2x2x2", 2), grid, 3)
    queue.check_client("another client", 3)
    queue.pump_once(0)
    assert queue.cancel(jobs[0])["state"] == "cancelled" and runner.cancelled == [jobs[0]]
    assert queue.cancel(jobs[2])["state"] == "cancelled" and runner.cancelled == [jobs[0]]  # was queued
    with pytest.raises(WrongState, match="already ended"):
        queue.cancel(jobs[0])
    with pytest.raises(NoSuchJob):
        queue.view("nonsense")
    queue.pump_once(0)  # jobs[1] takes the free slot; the server stops while it runs
    again, runner = _queue(tmp_path)
    assert [v["state"] for v in again.views()] == ["cancelled", "queued", "cancelled"]  # newest first
    assert json.loads((tmp_path / "jobs" / jobs[1] / "job.json").read_text())["state"] == "queued"
    (tmp_path / "jobs" / jobs[1] / "shape.npy").write_bytes(b"not an array")
    again.pump_once(0)
    assert "its shape is unreadable" in again.view(jobs[1])["error"] and runner.started == []


def test_uploads_and_print_settings_are_checked():
    limits = Limits(max_upload_bytes=100, max_voxels=64, max_time_limit=10.0, max_client_jobs=1)
    assert declared_too_large(str(100 + 65536 + 1), 100) and not declared_too_large("100", 100)
    assert not declared_too_large(None, 100) and not declared_too_large("-5", 100)
    with pytest.raises(TooLarge, match="limit of 100 bytes"):
        shape_grid(None, ("big.npy", b"\0" * 101), None, limits)
    with pytest.raises(TooLarge, match="125 voxels"):
        shape_grid("cube5", None, None, limits)
    assert shape_grid("cube4", None, None, limits)[1].sum() == 64
    check_print(10.0, 0.2)
    for size, gap in ((0.0, 0.0), (5.0, 5.0), (2000.0, 0.1), (5.0, -1.0)):
        with pytest.raises(RLLockError):
            check_print(size, gap)
    assert zip_name("0123456789ab", 10.0, 0.2) == "0123456789ab-pieces-10mm-gap0.2.zip"


# --- the routes, called in-process -----------------------------------------------------------------


def _call(app, method: str, path: str, body: bytes = b"", headers: dict | None = None) -> tuple[int, dict]:
    """One HTTP request through the ASGI app: (status, the JSON body)."""
    path, _, query = path.partition("?")
    scope = {
        "type": "http",
        "asgi": {"version": "3.0"},
        "http_version": "1.1",
        "method": method,
        "scheme": "http",
        "path": path,
        "raw_path": path.encode(),
        "query_string": query.encode(),
        "root_path": "",
        "headers": [(k.lower().encode(), v.encode()) for k, v in (headers or {}).items()],
        "client": ("10.0.0.1", 5000),
        "server": ("testserver", 80),
    }
    incoming = [{"type": "http.request", "body": body, "more_body": False}]
    sent: list[dict] = []

    async def receive() -> dict:
        return incoming.pop(0) if incoming else {"type": "http.disconnect"}

    async def send(message: dict) -> None:
        sent.append(message)

    asyncio.run(app(scope, receive, send))
    status = next(m["status"] for m in sent if m["type"] == "http.response.start")
    return status, json.loads(b"".join(m.get("body", b"") for m in sent if m["type"] == "http.response.body"))


def _form(fields: dict[str, str]) -> tuple[bytes, dict]:
    boundary = "rllockboundary"
    parts = [
        f'--{boundary}\r\nContent-Disposition: form-data; name="{k}"\r\n\r\n{v}\r\n'
        for k, v in fields.items()
    ]
    body = ("".join(parts) + f"--{boundary}--\r\n").encode()
    return body, {
        "content-type": f"multipart/form-data; boundary={boundary}",
        "content-length": str(len(body)),
    }


def test_the_routes_over_a_queue(tmp_path):
    queue, runner = _queue(tmp_path)
    limits = Limits(max_upload_bytes=1000, max_voxels=200, max_time_limit=120.0, max_client_jobs=1)
    app = make_api(Ingress(limits, queue, None, [], 0.0))
    status, body = _call(app, "GET", "/api/health")
    assert status == 200 and body["ok"] is True
    status, body = _call(app, "POST", "/api/jobs", b"", {"content-length": str(1000 + 65537)})
    assert (status, body) == (413, {"error": "the file is larger than the server's limit of 1,000 bytes"})
    assert _call(app, "POST", "/api/jobs", *_form({"shape": "cube4", "pieces": "six"}))[0] == 400
    status, body = _call(
        app, "POST", "/api/jobs", *_form({"shape": "cube4", "pieces": "6", "time_limit": "121"})
    )
    assert status == 400 and "at most 120" in body["error"]
    status, job = _call(app, "POST", "/api/jobs", *_form({"shape": "cube4", "pieces": "6"}))
    assert status == 201 and job["state"] == "queued" and job["N"] == 64 and "client" not in job
    status, body = _call(app, "POST", "/api/jobs", *_form({"shape": "cube4", "pieces": "6"}))
    assert status == 429 and "limit" in body["error"]
    assert _call(app, "GET", f"/api/jobs/{job['id']}/files/assembly.json")[0] == 409
    assert _call(app, "GET", f"/api/jobs/{job['id']}/pieces.zip?gap=20")[0] == 400
    assert _call(app, "GET", "/api/jobs/0123456789ab")[0] == 404
    assert _call(app, "POST", f"/api/jobs/{job['id']}/cancel")[1]["state"] == "cancelled"
    assert _call(app, "POST", f"/api/jobs/{job['id']}/cancel")[0] == 409
    assert [j["id"] for j in _call(app, "GET", "/api/jobs")[1]] == [job["id"]]
    assert runner.started == []
