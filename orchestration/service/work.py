"""The work of a `rllock serve` job: `run_job` (a solve or a generate, in a scratch folder, its
assemblies verified and returned as files), the Ray task that runs it on any node of the cluster, and
`RayRunner`, the job queue's way to start, wait for, collect and cancel those tasks.

A task sends its progress to the ingress (`Service.progress`) and returns its files; the ingress writes
them into the data folder, so that jobs may run anywhere while their files live in one place.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import ray
from ray import serve

from rllock.core.env import Task, make_task
from rllock.errors import RLLockError
from rllock.orchestration.service.jobs import ASSEMBLY, JobFailed
from rllock.orchestration.service.request import JobSpec

SERVICE, MODEL = "Service", "Model"  # the deployments' names in the application
GENERATE_BATCH = 8  # lockstep episodes of a generate job: one network request carries them all
PROGRESS_EVERY_S = 0.5

Report = Callable[[dict], None]
EvaluateFor = Callable[[Task], tuple[Any, list]]


# --- the work ----------------------------------------------------------------------------------------


def run_job(
    spec: JobSpec, grid: np.ndarray, report: Report, evaluate_for: EvaluateFor | None = None
) -> tuple[dict, dict[str, bytes]]:
    """(summary, files by relative path) of one job, run in a scratch folder: its assemblies, each
    verified and written with its picture. `report` takes progress as it comes; `evaluate_for(task)`
    (generate only) gives (the policy without weights, the batched network evaluation)."""
    pieces = spec.pieces if spec.pieces is not None else _suggested(spec, grid, report)
    task = make_task(grid, pieces, spec.removal, name=spec.shape)
    with tempfile.TemporaryDirectory(prefix="rllock-job-") as folder:
        out = Path(folder)
        if spec.method == "solve":
            summary = _solve(spec, task, out, report)
        else:
            assert evaluate_for is not None, "a generate job needs the model deployment"
            summary = _generate(spec, task, out, report, evaluate_for)
        files = {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}
    return summary, files


def _picture():
    from rllock.files.render import write_picture

    return write_picture


def _solve(spec: JobSpec, task: Task, out: Path, report: Report) -> dict:
    from rllock.files.assembly import write_assembly
    from rllock.search.solver import SearchConfig, SearchStats, search

    stats = SearchStats()
    start = time.monotonic()

    def progress(s: SearchStats) -> None:
        report(
            {
                "placed": s.placed,
                "pieces": task.pieces,
                "nodes": s.expansions,
                "restarts": s.restarts,
                "elapsed": round(time.monotonic() - start, 1),
            }
        )

    config = SearchConfig()
    for found in search(
        task, seed=spec.seed, time_limit=spec.time_limit, config=config, stats=stats, report=progress
    ):
        write_assembly(
            out / ASSEMBLY,
            found.labels,
            removal=task.removal,
            shape=spec.shape,
            method={"name": "search", **asdict(config), "service": True},
            seed=found.seed,
            timings={"seconds": round(found.seconds, 4), "node_expansions": found.expansions},
            picture=_picture(),
        )
        return {
            "assemblies": 1,
            "pieces": task.pieces,
            "seconds": round(time.monotonic() - start, 3),
            "nodes": stats.expansions,
        }
    text = (
        f"no valid assembly of {spec.shape} K={task.pieces} within {spec.time_limit:g} s: "
        f"best {stats.placed} of {task.pieces - 1} pieces placed"
    )
    offer = _offer(spec, task, report)
    if offer is None:
        raise NothingFound(f"{text}; give more time or another K")
    grown = "" if offer["thicken"] is None else f" with the thin parts grown (thicken {offer['thicken']})"
    raise NothingFound(
        f"{text}; K={offer['pieces']}{grown} works: pieces of {offer['piece_size']}, the last "
        f"{offer['last_size']}, found in {offer['seconds']} s",
        offer,
    )


class NothingFound(RLLockError):
    """A solve job's search found nothing; `offer`: the nearest task that works, when the probe found one
    (`rllock.search.probe`): its pieces, thicken, piece_size, last_size and seconds."""

    def __init__(self, message: str, offer: dict | None = None):
        super().__init__(message)
        self.offer = offer

    def __reduce__(self):  # Ray sends it back to the ingress
        return NothingFound, (str(self), self.offer)


def _suggested(spec: JobSpec, grid: np.ndarray, report: Report) -> int:
    """A solve job's K when it names none: the first of `rllock.search.probe.suggestions` (pieces of about
    20 voxels, then larger) that this search (its seed) finds an assembly for, on the job's one core."""
    from rllock.search.probe import SUGGESTED_SIZES, default_probe_seconds, suggest

    budget = default_probe_seconds(spec.time_limit)
    report({"placed": -1, "pieces": None, "choosing": round(budget)})
    found = suggest(grid, spec.removal, seed=spec.seed, budget=budget, workers=1)
    if found is None:
        raise NothingFound(
            f"no piece count for {spec.shape} with pieces of {SUGGESTED_SIZES[0]} to {SUGGESTED_SIZES[-1]} "
            f"voxels gave an assembly within {budget:g} s; give K, or grow its thin parts (thicken 3)"
        )
    return found.candidate.pieces


def _offer(spec: JobSpec, task: Task, report: Report) -> dict | None:
    """The nearest task that works (`rllock.search.probe`, on this job's one core, for
    `default_probe_seconds`): what `_solve` offers when its search found nothing."""
    from rllock.search.probe import default_probe_seconds, nearest_that_works

    budget = default_probe_seconds(spec.time_limit)
    report({"placed": -1, "pieces": task.pieces, "probe": round(budget)})
    found = nearest_that_works(
        task.topology.grid,
        task.removal,
        task.pieces,
        grown=spec.thicken is not None,
        seed=spec.seed,
        budget=budget,
        workers=1,
    )
    if found is None:
        return None
    c = found.candidate
    return {
        "pieces": c.pieces,
        "thicken": c.thicken if c.thicken is not None else spec.thicken,
        "piece_size": found.piece_size,
        "last_size": found.last_size,
        "seconds": round(found.seconds or 0.0, 1),
    }


def _generate(spec: JobSpec, task: Task, out: Path, report: Report, evaluate_for: EvaluateFor) -> dict:
    from rllock.search.inference import generate

    policy, searchers = evaluate_for(task)
    start = time.monotonic()

    def progress(episodes: int, valid: int, best: int) -> None:
        report(
            {
                "placed": best,
                "pieces": task.pieces,
                "episodes": episodes,
                "elapsed": round(time.monotonic() - start, 1),
            }
        )

    result = generate(
        policy,
        count=1,
        batch=GENERATE_BATCH,
        time_limit=spec.time_limit,
        seed=spec.seed,
        out=out,
        picture=_picture(),
        progress=False,
        report=progress,
        searchers=searchers,
    )
    if not result.valid:
        raise RLLockError(
            f"no valid assembly of {spec.shape} K={task.pieces} from {spec.checkpoint} in "
            f"{result.episodes} episodes ({spec.time_limit:g} s): best {result.best_placed} of "
            f"{task.pieces - 1} pieces placed; try the solver"
        )
    return {"assemblies": result.valid, "seconds": round(result.seconds, 3), "episodes": result.episodes}


# --- the job's side (a Ray task) ---------------------------------------------------------------------

# The compiled remote searches of this worker process, by shapes. Ray reuses a worker process for many
# tasks, and compiling a search costs seconds: this cache is what lets the second generate job of a
# shape in a worker start at once. It is the process's, by nature, so it lives at module level.
_COMPILED: dict[tuple, object] = {}


def _evaluate_for(model: Any, checkpoint: str) -> EvaluateFor:
    """`run_job`'s network for generate: the policy described by the model deployment, its evaluations
    sent to it (one request per simulation, all lockstep episodes in it)."""
    from rllock.search.remote import RemoteSearch, remote_searcher

    def evaluate_for(task: Task) -> tuple[Any, list]:
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
def _job_task(app: str, job_id: str, spec: JobSpec, grid: np.ndarray) -> tuple[dict, dict[str, bytes]]:
    from rllock.process import setup_jax_cache

    setup_jax_cache()
    service = serve.get_deployment_handle(SERVICE, app_name=app)
    model = serve.get_deployment_handle(MODEL, app_name=app)
    last = [0.0]

    def report(progress: dict) -> None:
        now = time.monotonic()
        if now - last[0] >= PROGRESS_EVERY_S:
            last[0] = now
            service.progress.remote(job_id, progress)

    evaluate_for = _evaluate_for(model, spec.checkpoint) if spec.checkpoint is not None else None
    return run_job(spec, grid, report, evaluate_for)


def failure(exc: BaseException) -> str:
    """A failed job's error in one line: the job's own RLLockError, or what happened to its worker."""
    cause = getattr(exc, "cause", None) or exc
    if isinstance(cause, RLLockError):
        return str(cause)
    if isinstance(exc, ray.exceptions.WorkerCrashedError | ray.exceptions.NodeDiedError):
        return "the job's worker process died"
    text = str(cause).strip().splitlines()
    return f"{type(cause).__name__}: {text[-1] if text else ''}"


class RayRunner:
    """Jobs as Ray tasks of `cpus` CPUs each, in the Serve application `app` (whose deployments they
    call back: the ingress for progress, the model for network evaluations)."""

    def __init__(self, app: str, cpus: float) -> None:
        self.app = app
        self.cpus = cpus

    def start(self, job_id: str, spec: JobSpec, grid: np.ndarray) -> ray.ObjectRef:
        return _job_task.options(num_cpus=self.cpus, name=f"rllock-job-{job_id}").remote(
            self.app, job_id, spec, grid
        )

    def ready(self, handles: list[ray.ObjectRef], timeout: float) -> list[ray.ObjectRef]:
        done, _ = ray.wait(handles, num_returns=len(handles), timeout=timeout)
        return done

    def result(self, handle: ray.ObjectRef) -> tuple[dict, dict[str, bytes]]:
        try:
            return ray.get(handle)
        except Exception as exc:  # the job's error, or its worker's death: the record says which
            cause = getattr(exc, "cause", None) or exc
            raise JobFailed(failure(exc), getattr(cause, "offer", None)) from None

    def cancel(self, handle: ray.ObjectRef) -> None:
        ray.cancel(handle, force=True)
