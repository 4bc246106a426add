"""`rllock serve`: the Ray Serve application. Two deployments: `Model` (`model.ModelServer`: checkpoints
by name, network evaluations batched across jobs) and `Service`, the HTTP ingress (FastAPI, OpenAPI at
/docs) that checks requests, keeps the job queue, runs each job as a Ray task with at most `max_jobs`
at once, and serves the web page at /.

A job's task sends its progress to `Service.progress` and returns its files; the ingress writes them
into the data folder (`jobs`), so jobs may run on any node of a cluster while their files live in one
place. Every error a client can cause is an HTTP 4xx with {"error": one line}, and no job.
"""

import asyncio
import io
import json
import logging
import math
import signal
import socket
import tempfile
import threading
import time
import uuid
import zipfile
from collections import deque
from dataclasses import asdict
from pathlib import Path

import numpy as np
import ray
from fastapi import FastAPI, File, Form, Request, UploadFile
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, Response, StreamingResponse
from ray import serve

from orchestration.service.jobs import (
    FINAL,
    GENERATE_BATCH,
    JOB_ID,
    SHAPE_NAMES,
    JobSpec,
    Limits,
    check_request,
    new_record,
    read_records,
    run_job,
    sensible_pieces,
    shape_grid,
    write_json,
)
from orchestration.service.model import ModelServer
from rllock.config import ServeConfig
from rllock.errors import RLLockError

log = logging.getLogger(__name__)
# In the replicas, Ray Serve's logger is the one with handlers (its log files, and the server's stderr).
replica_log = logging.getLogger("ray.serve.rllock")

APP = "rllock"
WEB = Path(__file__).resolve().parent / "web"
STATIC = {"app.js": "text/javascript", "style.css": "text/css"}
ASSEMBLY_FILES = {
    "assembly.json": "application/json",
    "assembly.puz": "text/plain",
    "assembly.png": "image/png",
}
PROGRESS_EVERY_S = 0.5
EVENTS_POLL_S = 0.25

api = FastAPI(
    title="RL-Lock",
    description="Interlocking assemblies from voxel shapes: jobs that solve or generate, their files, "
    "a web page.",
    version="0.1.0",
)


class ApiError(Exception):
    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status


UPLOAD_CAP = {"bytes": 0}  # the largest request body, set by the ingress from its config


@api.middleware("http")
async def _refuse_large_bodies(request: Request, call_next):
    """A body that says it is larger than the upload cap (plus room for the form's other fields) is
    refused before it is read, not after it was spooled to disk."""
    size = request.headers.get("content-length", "")
    if UPLOAD_CAP["bytes"] and size.isdigit() and int(size) > UPLOAD_CAP["bytes"] + 65536:
        message = f"the file is larger than the server's limit of {UPLOAD_CAP['bytes']:,} bytes"
        return JSONResponse({"error": message}, status_code=413)
    return await call_next(request)


@api.exception_handler(ApiError)
async def _api_error(request: Request, exc: ApiError) -> JSONResponse:
    return JSONResponse({"error": str(exc)}, status_code=exc.status)


@api.exception_handler(RequestValidationError)
async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    first = exc.errors()[0] if exc.errors() else {}
    where = ".".join(str(p) for p in first.get("loc", ())[1:]) or "request"
    return JSONResponse({"error": f"{where}: {first.get('msg', 'invalid')}"}, status_code=422)


def _number(name: str, text: str | None, kind: type, default=None):
    """A form field as `kind`, or `default` when empty; a one-line 400 otherwise."""
    if text is None or text.strip() == "":
        return default
    try:
        value = kind(text)
    except ValueError:
        raise ApiError(400, f"{name} must be a number, got {text[:40]!r}") from None
    if isinstance(value, float) and not math.isfinite(value):
        raise ApiError(400, f"{name} must be a finite number")
    return value


# --- the job's side (a Ray task) ---------------------------------------------------------------------

_COMPILED: dict[tuple, object] = {}  # the compiled remote searches of this worker process, by shapes


def _evaluate_for(model, checkpoint: str):
    """`run_job`'s network for generate: the policy described by the model deployment, its evaluations
    sent to it (one request per simulation, all lockstep episodes in it)."""
    from rllock.search.remote import RemoteSearch, remote_searcher

    def evaluate_for(task):
        key, policy = model.describe.remote(checkpoint, task).result()

        def evaluate(planes: np.ndarray):
            return model.evaluate.remote((key, planes)).result()

        shapes = (key, policy.task.piece_size, policy.mcts, GENERATE_BATCH)
        if shapes not in _COMPILED:
            _COMPILED[shapes] = RemoteSearch(
                evaluate, policy.net, policy.mcts, policy.task, GENERATE_BATCH, policy.method
            )
        return policy, [remote_searcher(_COMPILED[shapes], policy.task)]  # type: ignore[arg-type]

    return evaluate_for


@ray.remote(max_retries=0)
def _job_task(job_id: str, spec: dict, grid: np.ndarray):
    from rllock.process import setup_jax_cache

    setup_jax_cache()
    service = serve.get_deployment_handle("Service", app_name=APP)
    model = serve.get_deployment_handle("Model", app_name=APP)
    last = [0.0]

    def report(progress: dict) -> None:
        now = time.monotonic()
        if now - last[0] >= PROGRESS_EVERY_S:
            last[0] = now
            service.progress.remote(job_id, progress)

    job = JobSpec(**spec)
    evaluate_for = _evaluate_for(model, job.checkpoint) if job.checkpoint is not None else None
    return run_job(job, grid, report, evaluate_for)


def _failure(exc: BaseException) -> str:
    """A failed job's error in one line: the job's own RLLockError, or what happened to its worker."""
    cause = getattr(exc, "cause", None) or exc
    if isinstance(cause, RLLockError):
        return str(cause)
    if isinstance(exc, ray.exceptions.WorkerCrashedError | ray.exceptions.NodeDiedError):
        return "the job's worker process died"
    text = str(cause).strip().splitlines()
    return f"{type(cause).__name__}: {text[-1] if text else ''}"


def _stl_zip(assembly: Path, voxel_size: float, gap: float) -> bytes:
    """A zip of piece_NN.stl files and a README saying how they were made and checked."""
    from rllock.files.assembly import read_assembly
    from rllock.files.export import write_meshes

    labels, meta = read_assembly(assembly)
    buffer = io.BytesIO()
    with tempfile.TemporaryDirectory(prefix="rllock-stl-") as folder:
        paths = write_meshes(labels, "stl", folder, voxel_size, gap)
        with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
            for path in paths:
                archive.write(path, path.name)
            verification = meta.get("verification", {})
            archive.writestr(
                "README.txt",
                f"{len(paths)} pieces of {meta.get('shape')} (K={meta.get('K')}, "
                f"removal={meta.get('removal')}), "
                f"{voxel_size:g} mm voxels, {gap:g} mm clearance between neighbouring pieces.\n"
                f"Piece 1 is the key; take the pieces out in order 1, 2, ... K.\n"
                f"The assembly was verified valid by {verification.get('checker')} "
                f"v{verification.get('checker_version')} at {verification.get('verified_at')}.\n",
            )
    return buffer.getvalue()


# --- the ingress -------------------------------------------------------------------------------------


@serve.ingress(api)
class Service:
    """The HTTP API and the job queue. State lives in memory and in the data folder; the queue's pump
    (a thread) starts queued jobs as slots free and collects finished ones."""

    def __init__(self, config: dict, model) -> None:
        self.config = ServeConfig(**config)
        self.limits = Limits(
            int(self.config.max_upload_mb * 1e6), self.config.max_voxels, self.config.max_time_limit
        )
        UPLOAD_CAP["bytes"] = self.limits.max_upload_bytes
        self.model = model
        self.folder = Path(self.config.data) / "jobs"
        self.folder.mkdir(parents=True, exist_ok=True)
        self.lock = threading.RLock()
        records = read_records(self.folder)
        self.jobs: dict[str, dict] = {r["id"]: r for r in records}
        self.queue: deque[str] = deque(r["id"] for r in records if r["state"] == "queued")
        for job_id in self.queue:
            write_json(self.folder / job_id / "job.json", self.jobs[job_id])
        self.running: dict[str, ray.ObjectRef] = {}
        self.progress_of: dict[str, dict] = {}
        cpus = float(ray.cluster_resources().get("CPU", 1.0))
        self.max_jobs = self.config.max_jobs or max(1, int(2 * cpus))
        self.job_cpus = min(1.0, cpus / self.max_jobs)
        self.shape_rows = [self._shape_row(name) for name in SHAPE_NAMES]
        self.started = time.time()
        threading.Thread(target=self._pump, name="job-queue", daemon=True).start()
        replica_log.info(
            "%d jobs on record, %d queued; at most %d at once", len(records), len(self.queue), self.max_jobs
        )

    # -- the queue --

    def _pump(self) -> None:
        while True:
            try:
                self._pump_once()
            except Exception:  # the queue must outlive any one job's trouble; the log says what it was
                replica_log.exception("the job queue's pump")
                time.sleep(1.0)

    def _pump_once(self) -> None:
        with self.lock:
            refs = list(self.running.values())
        if refs:
            ready, _ = ray.wait(refs, num_returns=len(refs), timeout=0.2)
        else:
            time.sleep(0.2)
            ready = []
        for ref in ready:
            self._collect(ref)
        with self.lock:
            while self.queue and len(self.running) < self.max_jobs:
                self._start(self.queue.popleft())

    def _start(self, job_id: str) -> None:
        record = self.jobs[job_id]
        try:
            grid = np.load(self.folder / job_id / "shape.npy")
        except (OSError, ValueError) as exc:
            self._update(
                record, state="failed", finished=time.time(), error=f"its shape is unreadable: {exc}"
            )
            return
        self.running[job_id] = _job_task.options(num_cpus=self.job_cpus, name=f"rllock-job-{job_id}").remote(
            job_id, record["spec"], grid
        )
        self._update(record, state="running", started=time.time())

    def _collect(self, ref: ray.ObjectRef) -> None:
        with self.lock:
            job_id = next((j for j, r in self.running.items() if r == ref), None)
            if job_id is None:  # cancelled meanwhile
                return
        try:
            summary, files = ray.get(ref)
        except Exception as exc:  # the job's error, or its worker's death: the record says which
            with self.lock:
                if self.running.pop(job_id, None) is not None:
                    self._update(self.jobs[job_id], state="failed", finished=time.time(), error=_failure(exc))
            return
        for name, data in files.items():
            path = self.folder / job_id / name
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(data)
        with self.lock:
            if self.running.pop(job_id, None) is not None:
                self._update(self.jobs[job_id], state="done", finished=time.time(), result=summary)

    def _update(self, record: dict, **changes) -> None:
        record.update(changes)
        if "state" in changes:
            spec = record["spec"]
            replica_log.info(
                "job %s (%s %s K=%d): %s%s",
                record["id"],
                spec["method"],
                spec["shape"],
                spec["pieces"],
                record["state"],
                f": {record['error']}" if record["error"] else "",
            )
        if record["state"] in FINAL:
            self.progress_of.pop(record["id"], None)
        write_json(self.folder / record["id"] / "job.json", record)

    def progress(self, job_id: str, progress: dict) -> None:
        """A running job's progress (called by its task)."""
        with self.lock:
            if job_id in self.running:
                self.progress_of[job_id] = progress

    # -- helpers --

    def _record(self, job_id: str) -> dict:
        with self.lock:
            if not JOB_ID.match(job_id) or job_id not in self.jobs:
                raise ApiError(404, f"no job {job_id[:40]!r}")
            return self.jobs[job_id]

    def _view(self, record: dict) -> dict:
        with self.lock:
            view = {k: v for k, v in record.items() if k != "client"}
            view["progress"] = self.progress_of.get(record["id"])
            if record["state"] == "queued":
                view["queue_position"] = (
                    list(self.queue).index(record["id"]) + 1 if record["id"] in self.queue else None
                )
            if record["state"] == "done":
                base = f"/api/jobs/{record['id']}"
                view["files"] = {name: f"{base}/files/{name}" for name in ASSEMBLY_FILES} | {
                    "pieces.zip": f"{base}/pieces.zip"
                }
            return view

    @staticmethod
    def _shape_row(name: str) -> dict:
        from rllock.core.shapes import builtin_shape

        grid = builtin_shape(name)
        assert grid is not None
        n = int(grid.sum())
        return {"name": name, "N": n, "dimensions": list(grid.shape), "pieces": sensible_pieces(n)}

    async def _upload(self, file: UploadFile | None) -> tuple[str, bytes] | None:
        if file is None or not file.filename:
            return None
        data = await file.read(self.limits.max_upload_bytes + 1)
        if len(data) > self.limits.max_upload_bytes:
            raise ApiError(
                413, f"the file is larger than the server's limit of {self.limits.max_upload_bytes:,} bytes"
            )
        return file.filename, data

    async def _grid(self, shape: str | None, file: UploadFile | None, resolution: str | None):
        upload = await self._upload(file)
        try:
            return await asyncio.to_thread(
                shape_grid, shape or None, upload, _number("resolution", resolution, int), self.limits
            )
        except RLLockError as exc:
            status = 413 if "server's limit" in str(exc) else 400
            raise ApiError(status, str(exc)) from None

    # -- the API --

    @api.get("/", include_in_schema=False)
    def index(self) -> FileResponse:
        return FileResponse(WEB / "index.html", media_type="text/html")

    @api.get("/static/{name}", include_in_schema=False)
    def static(self, name: str) -> FileResponse:
        if name not in STATIC:
            raise ApiError(404, f"no file {name[:40]!r}")
        return FileResponse(WEB / name, media_type=STATIC[name])

    @api.get("/api/health")
    def health(self) -> dict:
        return {"ok": True, "up_seconds": round(time.time() - self.started, 1)}

    @api.get("/api/shapes")
    def shapes(self) -> list[dict]:
        """The built-in shapes: name, voxel count N, dimensions and the K that make sense."""
        return self.shape_rows

    @api.post("/api/shape")
    async def shape(
        self,
        shape: str | None = Form(None),
        resolution: str | None = Form(None),
        file: UploadFile | None = File(None),
    ) -> dict:
        """A shape (a built-in name, or an uploaded .puz/.vol/.npy/.stl/.obj) before any search: its voxel
        count N, dimensions, the K that make sense, and its voxels (x fastest, then y, then z)."""
        label, grid = await self._grid(shape, file, resolution)
        n = int(grid.sum())
        flat = np.flatnonzero(grid.transpose(2, 1, 0).ravel())  # x fastest
        return {
            "name": label,
            "N": n,
            "dimensions": list(grid.shape),
            "pieces": sensible_pieces(n),
            "voxels": flat.tolist(),
        }

    @api.post("/api/jobs", status_code=201)
    async def create(
        self,
        request: Request,
        pieces: str = Form(...),
        method: str = Form("solve"),
        shape: str | None = Form(None),
        removal: str = Form("straight"),
        resolution: str | None = Form(None),
        time_limit: str | None = Form(None),
        seed: str | None = Form(None),
        checkpoint: str | None = Form(None),
        file: UploadFile | None = File(None),
    ) -> dict:
        """A job: `solve` (the search solver) or `generate` (MCTS with a shipped checkpoint; default the
        one for the task, else `general`) on a built-in shape or an uploaded file, with K = `pieces`."""
        client = request.client.host if request.client else "unknown"
        self._check_client(client)
        label, grid = await self._grid(shape, file, resolution)
        spec = JobSpec(
            method=method,
            shape=label,
            pieces=_number("pieces", pieces, int),
            removal=removal,
            resolution=_number("resolution", resolution, int),
            time_limit=_number("time_limit", time_limit, float, 60.0),
            seed=_number("seed", seed, int, 0),
            checkpoint=checkpoint or None,
        )
        try:
            spec, _ = await asyncio.to_thread(check_request, spec, grid, self.limits)
        except RLLockError as exc:
            raise ApiError(400, str(exc)) from None
        job_id = uuid.uuid4().hex[:12]
        folder = self.folder / job_id
        folder.mkdir()
        np.save(folder / "shape.npy", grid)
        record = new_record(job_id, client, spec, int(grid.sum()))
        with self.lock:
            self._check_client(client)
            write_json(folder / "job.json", record)
            self.jobs[job_id] = record
            self.queue.append(job_id)
            return self._view(record)

    def _check_client(self, client: str) -> None:
        with self.lock:
            active = sum(1 for r in self.jobs.values() if r["client"] == client and r["state"] not in FINAL)
        if active >= self.config.max_client_jobs:
            raise ApiError(
                429, f"you have {active} jobs queued or running, the server's limit: wait for one to finish"
            )

    @api.get("/api/jobs")
    def list_jobs(self) -> list[dict]:
        """Every job, newest first."""
        with self.lock:
            return [self._view(r) for r in sorted(self.jobs.values(), key=lambda r: -r["created"])]

    @api.get("/api/jobs/{job_id}")
    def job(self, job_id: str) -> dict:
        """A job's request, state (queued, running, done, failed, cancelled), progress, result and files."""
        return self._view(self._record(job_id))

    @api.get("/api/jobs/{job_id}/events")
    async def events(self, job_id: str) -> StreamingResponse:
        """Server-sent events: the job's view (as GET /api/jobs/ID) each time it changes, until it ends."""
        record = self._record(job_id)

        async def stream():
            last = None
            while True:
                view = self._view(record)
                text = json.dumps(view)
                if text != last:
                    yield f"data: {text}\n\n"
                    last = text
                if view["state"] in FINAL:
                    return
                await asyncio.sleep(EVENTS_POLL_S)

        return StreamingResponse(
            stream(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"}
        )

    @api.post("/api/jobs/{job_id}/cancel")
    def cancel(self, job_id: str) -> dict:
        """Stop a queued or running job (a finished one stays as it is: 409)."""
        record = self._record(job_id)
        with self.lock:
            if record["state"] in FINAL:
                raise ApiError(409, f"job {job_id} has already ended ({record['state']})")
            if job_id in self.queue:
                self.queue.remove(job_id)
            ref = self.running.pop(job_id, None)
            if ref is not None:
                ray.cancel(ref, force=True)
            self._update(record, state="cancelled", finished=time.time())
            return self._view(record)

    def _done(self, job_id: str) -> Path:
        record = self._record(job_id)
        if record["state"] != "done":
            raise ApiError(409, f"job {job_id} has no files: it is {record['state']}")
        return self.folder / job_id / "assembly_001"

    @api.get("/api/jobs/{job_id}/files/{name}")
    def file(self, job_id: str, name: str) -> FileResponse:
        """The job's assembly: assembly.json (the labels and the verified disassembly), assembly.puz,
        assembly.png."""
        if name not in ASSEMBLY_FILES:
            raise ApiError(404, f"no file {name[:40]!r}: use one of {', '.join(ASSEMBLY_FILES)}")
        return FileResponse(
            self._done(job_id) / name, media_type=ASSEMBLY_FILES[name], filename=f"{job_id}-{name}"
        )

    @api.get("/api/jobs/{job_id}/pieces.zip")
    async def pieces(self, job_id: str, gap: str | None = None, voxel_size: str | None = None) -> Response:
        """Every piece as an STL file (millimetres), for printing: `voxel_size` mm voxels (default 10),
        shrunk to leave `gap` mm of clearance between neighbouring pieces (default 0.2)."""
        from rllock.files.export import PRINT_GAP

        size = _number("voxel_size", voxel_size, float, 10.0)
        clearance = _number("gap", gap, float, PRINT_GAP)
        if not 0 < size <= 1000:
            raise ApiError(400, "voxel_size must be more than 0 and at most 1000 mm")
        if not 0 <= clearance < size:
            raise ApiError(400, "gap must be at least 0 and smaller than voxel_size")
        folder = self._done(job_id)
        data = await asyncio.to_thread(_stl_zip, folder / "assembly.json", size, clearance)
        name = f"{job_id}-pieces-{size:g}mm-gap{clearance:g}.zip"
        return Response(
            data,
            media_type="application/zip",
            headers={"Content-Disposition": f'attachment; filename="{name}"'},
        )

    @api.get("/api/stats")
    async def stats(self) -> dict:
        """The model deployment's batches (network calls, requests and states per call) and the jobs."""
        with self.lock:
            states: dict[str, int] = {}
            for r in self.jobs.values():
                states[r["state"]] = states.get(r["state"], 0) + 1
        return {"model": await self.model.stats.remote(), "jobs": states, "max_jobs": self.max_jobs}


# --- running it ----------------------------------------------------------------------------------------


def application(config: ServeConfig):
    """The bound application: the model deployment and the ingress, on no CPUs of their own (the jobs
    take the cores)."""
    cpus = {"num_cpus": 0}
    model = serve.deployment(name="Model", max_ongoing_requests=1024, ray_actor_options=cpus)(ModelServer)
    service = serve.deployment(name="Service", max_ongoing_requests=1024, ray_actor_options=cpus)(Service)
    return service.bind(asdict(config), model.bind())


def check_port(host: str, port: int) -> None:
    """A port something already listens on is one line, before Ray starts."""
    with socket.socket() as s:
        try:
            s.bind((host, port))
        except OSError as exc:
            raise RLLockError(
                f"cannot listen on {host}:{port}: {exc.strerror or exc} (give another --port)"
            ) from None


def serve_forever(config: ServeConfig) -> int:
    """Start Ray (or join --address), run the application until SIGINT or SIGTERM, then tear it down."""
    from orchestration.pool import start_ray

    config = ServeConfig(**{**asdict(config), "data": str(Path(config.data).resolve())})
    check_port(config.host, config.port)
    Path(config.data).mkdir(parents=True, exist_ok=True)
    started = start_ray(config.address)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        serve.start(http_options={"host": config.host, "port": config.port})
        serve.run(application(config), name=APP, route_prefix="/", blocking=False)
        log.info(
            "serving on http://%s:%d/ (API: /docs); data in %s; Ctrl-C stops",
            config.host,
            config.port,
            config.data,
        )
        while not stop.wait(0.5):
            pass
        log.info("stopping: queued and running jobs stay queued for the next start")
    finally:
        # Our own Ray instance goes whole (Serve's proxy and replicas with it); on a cluster we joined,
        # only our application is taken down.
        if started:
            ray.shutdown()
        else:
            serve.delete(APP)
    return 0
