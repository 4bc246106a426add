"""`rllock serve`: the Ray Serve application. Two deployments: `Model` (`model.ModelServer`: checkpoints
by name, network evaluations batched across jobs) and `Service`, the HTTP ingress (FastAPI, OpenAPI at
/docs), whose routes check requests and hand jobs to the queue (`jobs.JobQueue`), which runs each as a
Ray task (`work.RayRunner`) with at most `max_jobs` at once; / serves the web page.

The FastAPI app is built in the replica from the server's config (`make_api`), so that the routes and
the body-size guard take their limits from what they were given rather than from a module's state.
Every error a client can cause is an HTTP 4xx with {"error": one line}, and no job.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import signal
import socket
import threading
import time
from collections.abc import Awaitable, Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import ray
from fastapi import FastAPI, File, Form, Request, UploadFile
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, Response, StreamingResponse
from ray import serve

from rllock.config import ServeConfig
from rllock.errors import RLLockError
from rllock.orchestration.service.files import check_print, declared_too_large, read_upload, stl_zip, zip_name
from rllock.orchestration.service.jobs import (
    ASSEMBLY_FILES,
    FINAL,
    JobQueue,
    NoSuchJob,
    TooManyJobs,
    WrongState,
)
from rllock.orchestration.service.model import ModelServer
from rllock.orchestration.service.request import (
    JobSpec,
    Limits,
    TooLarge,
    builtin_rows,
    check_request,
    shape_grid,
    shape_summary,
    too_large,
)
from rllock.orchestration.service.work import MODEL, SERVICE, RayRunner

log = logging.getLogger(__name__)
# In the replicas, Ray Serve's logger is the one with handlers (its log files, and the server's stderr).
replica_log = logging.getLogger("ray.serve.rllock")

APP = "rllock"
WEB = Path(__file__).resolve().parent / "web"
STATIC: Mapping[str, str] = {"app.js": "text/javascript", "style.css": "text/css"}
EVENTS_POLL_S = 0.25
STATUS: Mapping[type[Exception], int] = {NoSuchJob: 404, WrongState: 409, TooLarge: 413, TooManyJobs: 429}
"""The HTTP status of each refusal the queue and the upload reader raise."""


class ApiError(Exception):
    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status


@dataclass(frozen=True)
class Ingress:
    """What the routes serve from: the request limits, the job queue, the model deployment's handle (for
    its statistics), the built-in shapes' rows, and when the server started."""

    limits: Limits
    jobs: JobQueue
    model: Any
    shape_rows: list[dict]
    started: float


def _number(name: str, text: str | None, kind: type, default: Any = None) -> Any:
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


def _status(exc: Exception) -> int:
    return next(STATUS[kind] for kind in type(exc).__mro__ if kind in STATUS)


@contextmanager
def _refusals() -> Iterator[None]:
    """A check's one-line error as the client's 4xx: 413 for a size limit, 400 for anything else."""
    try:
        yield
    except RLLockError as exc:
        raise ApiError(413 if isinstance(exc, TooLarge) else 400, str(exc)) from None


def make_api(ingress: Ingress) -> FastAPI:
    """The HTTP API and the page over `ingress`."""
    api = FastAPI(
        title="RL-Lock",
        description="Interlocking assemblies from voxel shapes: jobs that solve or generate, their files, "
        "a web page.",
        version="0.1.0",
    )
    _add_guards(api, ingress.limits.max_upload_bytes)
    _add_page(api)
    _add_shapes(api, ingress)
    _add_jobs(api, ingress)
    _add_files(api, ingress)
    return api


def _add_guards(api: FastAPI, cap: int) -> None:
    """The body-size guard and the handlers that turn refusals into {"error": one line}."""

    @api.middleware("http")
    async def _refuse_large_bodies(request: Request, call_next: Callable[[Request], Awaitable[Response]]):
        if declared_too_large(request.headers.get("content-length"), cap):
            return JSONResponse({"error": too_large(cap)}, status_code=413)
        return await call_next(request)

    async def refused(request: Request, exc: Exception) -> JSONResponse:
        status = exc.status if isinstance(exc, ApiError) else _status(exc)
        return JSONResponse({"error": str(exc)}, status_code=status)

    kinds: list[type[Exception]] = [ApiError, *STATUS]
    for kind in kinds:
        api.add_exception_handler(kind, refused)

    @api.exception_handler(RequestValidationError)
    async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
        first = exc.errors()[0] if exc.errors() else {}
        where = ".".join(str(p) for p in first.get("loc", ())[1:]) or "request"
        return JSONResponse({"error": f"{where}: {first.get('msg', 'invalid')}"}, status_code=422)


def _add_page(api: FastAPI) -> None:
    @api.get("/", include_in_schema=False)
    def index() -> FileResponse:
        return FileResponse(WEB / "index.html", media_type="text/html")

    @api.get("/static/{name}", include_in_schema=False)
    def static(name: str) -> FileResponse:
        if name not in STATIC:
            raise ApiError(404, f"no file {name[:40]!r}")
        return FileResponse(WEB / name, media_type=STATIC[name])


async def _grid(
    limits: Limits,
    shape: str | None,
    file: UploadFile | None,
    resolution: str | None,
    thicken: str | None = None,
) -> tuple[str, np.ndarray]:
    """The request's shape: its display name and voxel grid, from a built-in name or the uploaded file,
    its thin parts grown when `thicken` says so."""
    with _refusals():
        upload = await read_upload(file, limits.max_upload_bytes)
        width = _number("thicken", thicken, int)
        return await asyncio.to_thread(
            shape_grid, shape or None, upload, _number("resolution", resolution, int), limits, width
        )


def _add_shapes(api: FastAPI, ingress: Ingress) -> None:
    @api.get("/api/health")
    def health() -> dict:
        return {"ok": True, "up_seconds": round(time.time() - ingress.started, 1)}

    @api.get("/api/shapes")
    def shapes() -> list[dict]:
        """The built-in shapes: name, voxel count N, dimensions and the K that make sense."""
        return ingress.shape_rows

    @api.post("/api/shape")
    async def shape(
        shape: str | None = Form(None),
        resolution: str | None = Form(None),
        thicken: str | None = Form(None),
        file: UploadFile | None = File(None),
    ) -> dict:
        """A shape (a built-in name, or an uploaded .puz/.vol/.npy file or mesh, its thin parts grown to
        `thicken` when given) before any search: its voxel count N, dimensions, the K that make sense,
        how many voxels are thin, and its voxels (x fastest, then y, then z)."""
        label, grid = await _grid(ingress.limits, shape, file, resolution, thicken)
        flat = np.flatnonzero(grid.transpose(2, 1, 0).ravel())  # x fastest
        return shape_summary(label, grid) | {"voxels": flat.tolist()}


def _add_jobs(api: FastAPI, ingress: Ingress) -> None:
    jobs, limits = ingress.jobs, ingress.limits

    @api.post("/api/jobs", status_code=201)
    async def create(
        request: Request,
        pieces: str | None = Form(None),
        method: str = Form("solve"),
        shape: str | None = Form(None),
        removal: str = Form("straight"),
        resolution: str | None = Form(None),
        time_limit: str | None = Form(None),
        seed: str | None = Form(None),
        checkpoint: str | None = Form(None),
        thicken: str | None = Form(None),
        file: UploadFile | None = File(None),
    ) -> dict:
        """A job: `solve` (the search solver) or `generate` (MCTS with a shipped checkpoint; default the
        one for the task, else `general`) on a built-in shape or an uploaded file, with K = `pieces`; a solve
        without `pieces` takes the first K of pieces of about 20 voxels, then larger, that a probe finds an
        assembly for (`rllock.search.probe.suggestions`)."""
        client = request.client.host if request.client else "unknown"
        jobs.check_client(client, limits.max_client_jobs)  # before the upload is read and voxelized
        label, grid = await _grid(limits, shape, file, resolution, thicken)
        spec = JobSpec(
            method=method,
            shape=label,
            pieces=_number("pieces", pieces, int),
            removal=removal,
            resolution=_number("resolution", resolution, int),
            time_limit=_number("time_limit", time_limit, float, 60.0),
            seed=_number("seed", seed, int, 0),
            checkpoint=checkpoint or None,
            thicken=_number("thicken", thicken, int),
        )
        with _refusals():
            spec = await asyncio.to_thread(check_request, spec, grid, limits)
        return jobs.submit(client, spec, grid, limits.max_client_jobs)

    @api.get("/api/jobs")
    def list_jobs() -> list[dict]:
        """Every job, newest first."""
        return jobs.views()

    @api.get("/api/jobs/{job_id}")
    def job(job_id: str) -> dict:
        """A job's request, state (queued, running, done, failed, cancelled), progress, result and files."""
        return jobs.view(job_id)

    @api.get("/api/jobs/{job_id}/events")
    async def events(job_id: str) -> StreamingResponse:
        """Server-sent events: the job's view (as GET /api/jobs/ID) each time it changes, until it ends."""
        jobs.record(job_id)  # a 404 now, not an empty stream

        async def stream():
            last = None
            while True:
                view = jobs.view(job_id)
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
    def cancel(job_id: str) -> dict:
        """Stop a queued or running job (a finished one stays as it is: 409)."""
        return jobs.cancel(job_id)

    @api.get("/api/stats")
    async def stats() -> dict:
        """The model deployment's batches (network calls, requests and states per call) and the jobs."""
        model = await ingress.model.stats.remote()
        return {"model": model, "jobs": jobs.counts(), "max_jobs": jobs.max_jobs}


def _add_files(api: FastAPI, ingress: Ingress) -> None:
    jobs = ingress.jobs

    @api.get("/api/jobs/{job_id}/files/{name}")
    def file(job_id: str, name: str) -> FileResponse:
        """The job's assembly: assembly.json (the labels and the verified disassembly), assembly.puz,
        assembly.png."""
        if name not in ASSEMBLY_FILES:
            raise ApiError(404, f"no file {name[:40]!r}: use one of {', '.join(ASSEMBLY_FILES)}")
        return FileResponse(
            jobs.assembly(job_id) / name, media_type=ASSEMBLY_FILES[name], filename=f"{job_id}-{name}"
        )

    @api.get("/api/jobs/{job_id}/pieces.zip")
    async def pieces(job_id: str, gap: str | None = None, voxel_size: str | None = None) -> Response:
        """Every piece as an STL file (millimetres), for printing: `voxel_size` mm voxels (default 10),
        shrunk to leave `gap` mm of clearance between neighbouring pieces (default 0.2)."""
        from rllock.files.export import PRINT_GAP

        size = _number("voxel_size", voxel_size, float, 10.0)
        clearance = _number("gap", gap, float, PRINT_GAP)
        with _refusals():
            check_print(size, clearance)
        folder = jobs.assembly(job_id)
        data = await asyncio.to_thread(stl_zip, folder / "assembly.json", size, clearance)
        return Response(
            data,
            media_type="application/zip",
            headers={"Content-Disposition": f'attachment; filename="{zip_name(job_id, size, clearance)}"'},
        )


# --- the deployments -----------------------------------------------------------------------------------


@serve.ingress()
class Service:
    """The ingress deployment: the job queue (its pump a thread of this replica) and the FastAPI app
    built over it when the replica starts."""

    def __init__(self, config: dict, model: Any) -> None:
        settings = ServeConfig(**config)
        cpus = float(ray.cluster_resources().get("CPU", 1.0))
        max_jobs = settings.max_jobs or max(1, int(2 * cpus))
        runner = RayRunner(APP, min(1.0, cpus / max_jobs))
        self.jobs = JobQueue(Path(settings.data) / "jobs", runner, max_jobs)
        self.ingress = Ingress(Limits.of(settings), self.jobs, model, builtin_rows(), time.time())
        self.jobs.start_pump()
        counts = self.jobs.counts()
        replica_log.info(
            "%d jobs on record, %d queued; at most %d at once",
            sum(counts.values()),
            counts.get("queued", 0),
            max_jobs,
        )

    def progress(self, job_id: str, progress: dict) -> None:
        """A running job's progress (called by its task)."""
        self.jobs.progress(job_id, progress)

    def __serve_build_asgi_app__(self) -> FastAPI:
        return make_api(self.ingress)


def application(config: ServeConfig):
    """The bound application: the model deployment and the ingress, on no CPUs of their own (the jobs
    take the cores)."""
    cpus = {"num_cpus": 0}
    model = serve.deployment(name=MODEL, max_ongoing_requests=1024, ray_actor_options=cpus)(ModelServer)
    service = serve.deployment(name=SERVICE, max_ongoing_requests=1024, ray_actor_options=cpus)(Service)
    return service.bind(asdict(config), model.bind())


# --- running it ----------------------------------------------------------------------------------------


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
    from rllock.orchestration.pool import start_ray

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
