"""Jobs of `rllock serve`: what a request asks for (checked before any job exists), a job's record on
disk, and the work itself (`run_job`, in a Ray task).

A job lives in DATA/jobs/<id>/: job.json (its request, state and result, replaced atomically on every
change), shape.npy (the voxel grid, so that a queued job can run after a restart), and once done the
files of its assemblies, assembly_001/ (assembly.json, assembly.puz, assembly.png), each verified by
the full verifier before it is written. An uploaded file is voxelized when the request comes, under a
name of the server's own: its name is shown, never used as a path.
"""

from __future__ import annotations

import json
import math
import os
import re
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from rllock.core.env import Task, make_task
from rllock.core.reference_checkers import REMOVAL_MODES
from rllock.core.shapes import VENDORED_SHAPES, builtin_shape
from rllock.errors import RLLockError

METHODS = ("solve", "generate")
FINAL = frozenset({"done", "failed", "cancelled"})
UPLOAD_SUFFIXES = (".puz", ".vol", ".npy", ".stl", ".obj")
JOB_ID = re.compile(r"^[0-9a-f]{12}$")
SHAPE_NAMES = ("cube4", "cube5", "cube6", "ring", "stairs", "tube", *VENDORED_SHAPES)
"""The built-in shapes the web page offers (any cubeN and box:WxHxD are accepted too)."""
GENERATE_BATCH = 8  # lockstep episodes of a generate job: one network request carries them all


@dataclass(frozen=True)
class Limits:
    """What one request may ask of the server (from `rllock.config.ServeConfig`)."""

    max_upload_bytes: int
    max_voxels: int
    max_time_limit: float


@dataclass(frozen=True)
class JobSpec:
    """A job's request, checked (`check_request`)."""

    method: str
    shape: str  # a built-in name, or the uploaded file's name (shown only)
    pieces: int
    removal: str = "straight"
    resolution: int | None = None
    time_limit: float = 60.0
    seed: int = 0
    checkpoint: str | None = None  # generate: a shipped checkpoint; None before `check_request`


def shape_grid(name: str | None, upload: tuple[str, bytes] | None, resolution: int | None, limits: Limits):
    """(the shape's display name, its voxel grid) from a built-in name or an uploaded file's (name, bytes);
    a one-line error for anything else. A name never reads a file: only built-in shapes have names."""
    if (name is None) == (upload is None):
        raise RLLockError("give either a shape name or a file")
    if upload is None:
        assert name is not None
        if resolution is not None:
            raise RLLockError("a resolution applies only to uploaded .stl and .obj meshes")
        grid = builtin_shape(name)
        if grid is None:
            raise RLLockError(
                f"unknown shape {name!r}: use one of {', '.join(SHAPE_NAMES)}, cubeN or box:WxHxD"
            )
        label = name
    else:
        label, data = upload
        label = display_name(label)
        suffix = Path(label).suffix.lower()
        if suffix not in UPLOAD_SUFFIXES:
            raise RLLockError(f"unsupported file {label!r}: use {', '.join(UPLOAD_SUFFIXES)}")
        if len(data) > limits.max_upload_bytes:
            raise RLLockError(
                f"the file is larger than the server's limit of {limits.max_upload_bytes:,} bytes"
            )
        grid = _read_upload(label, suffix, data, resolution)
    grid = np.asarray(grid, dtype=bool)
    n = int(grid.sum())
    if n > limits.max_voxels:
        raise RLLockError(
            f"the shape has {n:,} voxels, more than the server's limit of {limits.max_voxels:,}"
        )
    return label, grid


def display_name(name: str) -> str:
    """The last part of an uploaded file's name, printable, at most 80 characters."""
    base = re.split(r"[\\/]", name or "")[-1]
    cleaned = "".join(c for c in base if c.isprintable())[-80:]
    return cleaned or "upload"


def _read_upload(label: str, suffix: str, data: bytes, resolution: int | None) -> np.ndarray:
    from rllock.core.shapes import load_shape

    with tempfile.TemporaryDirectory(prefix="rllock-upload-") as folder:
        path = Path(folder) / f"shape{suffix}"
        path.write_bytes(data)
        try:
            return load_shape(str(path), resolution)
        except RLLockError as exc:
            raise RLLockError(str(exc).replace(str(path), label)) from None
        except (ValueError, IndexError, KeyError, UnicodeDecodeError, EOFError) as exc:
            # A parser's own complaint about a malformed file, in one line.
            raise RLLockError(
                f"cannot read {label!r}: {str(exc).splitlines()[0] if str(exc) else exc}"
            ) from None


def sensible_pieces(n: int) -> dict[str, int]:
    """The K a user would start from for N voxels: pieces of 4 to 40 voxels (`low` to `high`); suggested,
    pieces of about 20 voxels, where the solver is quick on most shapes (smaller pieces in thin parts
    often take minutes: docs/benchmarks.md); `max` is N, the largest K there is."""
    low = max(2, math.ceil(n / 40))
    high = max(low, n // 4)
    suggested = min(max(round(n / 20), low), high)
    return {"min": 2, "max": n, "low": low, "high": min(high, n), "suggested": min(suggested, n)}


def check_request(spec: JobSpec, grid: np.ndarray, limits: Limits) -> tuple[JobSpec, Task]:
    """The spec with its checkpoint chosen, and its task, after every check that can fail before a
    search: the method, K against N, the removal mode, the time limit, a task with no assembly, and for
    generate a shipped checkpoint that plays the task."""
    from rllock.core.feasibility import check_feasible

    if spec.method not in METHODS:
        raise RLLockError(f"unknown method {spec.method!r}: use one of {', '.join(METHODS)}")
    if spec.removal not in REMOVAL_MODES:
        raise RLLockError(f"unknown removal mode {spec.removal!r}: use one of {', '.join(REMOVAL_MODES)}")
    if not (math.isfinite(spec.time_limit) and 0 < spec.time_limit <= limits.max_time_limit):
        raise RLLockError(f"the time limit must be more than 0 and at most {limits.max_time_limit:g} s")
    task = make_task(grid, spec.pieces, spec.removal, name=spec.shape)
    check_feasible(task)
    if spec.method == "generate":
        from rllock.files.checkpoint import SHIPPED, read_metadata, shipped_names
        from rllock.search.serving import checkpoint_for, served

        if spec.checkpoint is None:
            return JobSpec(**{**asdict(spec), "checkpoint": checkpoint_for(task)}), task
        if spec.checkpoint not in shipped_names():
            raise RLLockError(
                f"unknown checkpoint {spec.checkpoint!r}: use one of {', '.join(shipped_names())}"
            )
        served(read_metadata(SHIPPED / spec.checkpoint), SHIPPED / spec.checkpoint, task)
    elif spec.checkpoint is not None:
        raise RLLockError("a checkpoint applies only to the generate method")
    return spec, task


# --- records on disk ---------------------------------------------------------------------------------


def new_record(job_id: str, client: str, spec: JobSpec, n: int) -> dict:
    return {
        "id": job_id,
        "client": client,
        "spec": asdict(spec),
        "N": n,
        "state": "queued",
        "created": time.time(),
        "started": None,
        "finished": None,
        "error": None,
        "result": None,
    }


def write_json(path: Path, doc: dict) -> None:
    """`doc` written to `path` whole or not at all (a crash never leaves half a record)."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(doc, indent=1))
    os.replace(tmp, path)


def read_records(jobs: Path) -> list[dict]:
    """Every readable job record under `jobs`, oldest first. A job the server was running or holding in
    its queue when it stopped is queued again: its request and shape are on disk."""
    records = []
    for path in sorted(jobs.glob("*/job.json")):
        try:
            record = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError):
            continue
        if not (isinstance(record, dict) and JOB_ID.match(str(record.get("id", "")))):
            continue
        if record["state"] not in FINAL:
            record.update(state="queued", started=None)
        records.append(record)
    return sorted(records, key=lambda r: r["created"])


# --- the work ----------------------------------------------------------------------------------------

Report = Callable[[dict], None]


def run_job(
    spec: JobSpec, grid: np.ndarray, report: Report, evaluate_for=None
) -> tuple[dict, dict[str, bytes]]:
    """(summary, files by relative path) of one job, run in a scratch folder: its assemblies, each
    verified and written with its picture. `report` takes progress as it comes; `evaluate_for(task)`
    (generate only) gives (the policy without weights, the batched network evaluation)."""
    task = make_task(grid, spec.pieces, spec.removal, name=spec.shape)
    with tempfile.TemporaryDirectory(prefix="rllock-job-") as folder:
        out = Path(folder)
        if spec.method == "solve":
            summary = _solve(spec, task, out, report)
        else:
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
            out / "assembly_001",
            found.labels,
            removal=task.removal,
            shape=spec.shape,
            method={"name": "search", **asdict(config), "service": True},
            seed=found.seed,
            timings={"seconds": round(found.seconds, 4), "node_expansions": found.expansions},
            picture=_picture(),
        )
        return {"assemblies": 1, "seconds": round(time.monotonic() - start, 3), "nodes": stats.expansions}
    raise RLLockError(
        f"no valid assembly of {spec.shape} K={task.pieces} within {spec.time_limit:g} s: "
        f"best {stats.placed} of {task.pieces - 1} pieces placed; give more time or another K"
    )


def _generate(spec: JobSpec, task: Task, out: Path, report: Report, evaluate_for) -> dict:
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
