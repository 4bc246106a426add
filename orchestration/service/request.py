"""What a request to `rllock serve` asks for, checked before any job exists: the server's limits, a
shape from a built-in name or an uploaded file, and a job's spec. Every refusal is an `RLLockError` of
one line, so that a bad request costs the client a message and the server no job; `TooLarge` marks the
ones that break a size limit (HTTP 413 rather than 400).

An uploaded file is voxelized when the request comes, under a name of the server's own: its name is
shown, never used as a path.
"""

from __future__ import annotations

import math
import re
import tempfile
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from rllock.config import ServeConfig
from rllock.core.env import make_task
from rllock.core.reference_checkers import REMOVAL_MODES
from rllock.core.shapes import MESH_FORMATS, MESH_SUFFIXES, VENDORED_SHAPES, builtin_shape
from rllock.errors import RLLockError

METHODS = ("solve", "generate")
UPLOAD_SUFFIXES = (".puz", ".vol", ".npy", *MESH_SUFFIXES)
SHAPE_NAMES = ("cube4", "cube5", "cube6", "ring", "stairs", "tube", *VENDORED_SHAPES)
"""The built-in shapes the web page offers (any cubeN and box:WxHxD are accepted too)."""


class TooLarge(RLLockError):
    """A request over one of the server's size limits: the client must send less, not something else."""


@dataclass(frozen=True)
class Limits:
    """What one request may ask of the server, read once from its `ServeConfig` and handed to whatever
    checks requests (the routes, the body-size guard), so that no module holds it."""

    max_upload_bytes: int
    max_voxels: int
    max_time_limit: float
    max_client_jobs: int

    @classmethod
    def of(cls, config: ServeConfig) -> Limits:
        return cls(
            int(config.max_upload_mb * 1e6), config.max_voxels, config.max_time_limit, config.max_client_jobs
        )


@dataclass(frozen=True)
class JobSpec:
    """A job's request, checked (`check_request`)."""

    method: str
    shape: str  # a built-in name, or the uploaded file's name (shown only)
    pieces: int | None  # None: a solve job takes the first K a probe finds an assembly for (`run_job`)
    removal: str = "straight"
    resolution: int | None = None
    time_limit: float = 60.0
    seed: int = 0
    checkpoint: str | None = None  # generate: a shipped checkpoint; None before `check_request`
    thicken: int | None = None  # the shape's thin parts were grown to this width (`shape_grid`)


def too_large(limit: int) -> str:
    """The one line for an upload over `limit` bytes, the same whichever check catches it."""
    return f"the file is larger than the server's limit of {limit:,} bytes"


def shape_grid(
    name: str | None,
    upload: tuple[str, bytes] | None,
    resolution: int | None,
    limits: Limits,
    thicken: int | None = None,
) -> tuple[str, np.ndarray]:
    """(the shape's display name, its voxel grid) from a built-in name or an uploaded file's (name, bytes),
    its thin parts grown to `thicken` when given (`rllock.core.thickness`); a one-line error for anything
    else. A name never reads a file: only built-in shapes have names."""
    if thicken is not None and thicken < 2:
        raise RLLockError(f"thicken takes a width of at least 2 voxels, got {thicken}")
    if (name is None) == (upload is None):
        raise RLLockError("give either a shape name or a file")
    if upload is None:
        assert name is not None
        if resolution is not None:
            raise RLLockError(f"a resolution applies only to uploaded meshes ({MESH_FORMATS})")
        grid = builtin_shape(name)
        if grid is None:
            raise RLLockError(
                f"unknown shape {name!r}: use one of {', '.join(SHAPE_NAMES)}, cubeN or box:WxHxD"
            )
        label = name
    else:
        label = display_name(upload[0])
        suffix = Path(label).suffix.lower()
        if suffix not in UPLOAD_SUFFIXES:
            raise RLLockError(f"unsupported file {label!r}: use {', '.join(UPLOAD_SUFFIXES)}")
        if len(upload[1]) > limits.max_upload_bytes:
            raise TooLarge(too_large(limits.max_upload_bytes))
        grid = _read_upload(label, suffix, upload[1], resolution)
    grid = np.asarray(grid, dtype=bool)
    if thicken is not None:
        from rllock.core.thickness import thicken as grow

        grid = grow(grid, thicken)
    n = int(grid.sum())
    if n > limits.max_voxels:
        raise TooLarge(f"the shape has {n:,} voxels, more than the server's limit of {limits.max_voxels:,}")
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
    are often much slower); `max` is N, the largest K there is."""
    low = max(2, math.ceil(n / 40))
    high = max(low, n // 4)
    suggested = min(max(round(n / 20), low), high)
    return {"min": 2, "max": n, "low": low, "high": min(high, n), "suggested": min(suggested, n)}


def shape_summary(label: str, grid: np.ndarray) -> dict:
    """A shape as the page lists it: name, voxel count N, dimensions, the K that make sense, how many
    voxels lie in thin parts (arms, legs, ears: `rllock.core.thickness`), and whether they are enough for
    growing them to help, with the pieces a solve picks first."""
    from rllock.core.thickness import thin_matters, thin_voxels
    from rllock.search.probe import SUGGESTED_SIZES

    n = int(grid.sum())
    thin = int(thin_voxels(grid).sum())
    return {
        "name": label,
        "N": n,
        "dimensions": list(grid.shape),
        "pieces": sensible_pieces(n),
        "thin": thin,
        "thin_matters": thin_matters(thin, n, SUGGESTED_SIZES[0]),
    }


def builtin_rows() -> list[dict]:
    """`shape_summary` of every shape the page offers by name."""
    rows = []
    for name in SHAPE_NAMES:
        grid = builtin_shape(name)
        assert grid is not None
        rows.append(shape_summary(name, grid))
    return rows


def check_request(spec: JobSpec, grid: np.ndarray, limits: Limits) -> JobSpec:
    """The spec with its checkpoint chosen, after every check that can fail before a search: the method,
    K against N, the removal mode, the time limit, a task with no assembly, and for generate a shipped
    checkpoint that plays the task."""
    from rllock.core.feasibility import check_feasible

    if spec.method not in METHODS:
        raise RLLockError(f"unknown method {spec.method!r}: use one of {', '.join(METHODS)}")
    if spec.removal not in REMOVAL_MODES:
        raise RLLockError(f"unknown removal mode {spec.removal!r}: use one of {', '.join(REMOVAL_MODES)}")
    if not (math.isfinite(spec.time_limit) and 0 < spec.time_limit <= limits.max_time_limit):
        raise RLLockError(f"the time limit must be more than 0 and at most {limits.max_time_limit:g} s")
    if spec.pieces is None:
        if spec.method != "solve":
            raise RLLockError("give the piece count K: only the solver tries piece counts itself")
        if spec.checkpoint is not None:
            raise RLLockError("a checkpoint applies only to the generate method")
        return spec
    task = make_task(grid, spec.pieces, spec.removal, name=spec.shape)
    check_feasible(task)
    if spec.method == "generate":
        from rllock.files.checkpoint import SHIPPED, read_metadata, shipped_names
        from rllock.search.serving import checkpoint_for, served

        if spec.checkpoint is None:
            return replace(spec, checkpoint=checkpoint_for(task))
        if spec.checkpoint not in shipped_names():
            raise RLLockError(
                f"unknown checkpoint {spec.checkpoint!r}: use one of {', '.join(shipped_names())}"
            )
        served(read_metadata(SHIPPED / spec.checkpoint), SHIPPED / spec.checkpoint, task)
    elif spec.checkpoint is not None:
        raise RLLockError("a checkpoint applies only to the generate method")
    return spec


LATER_FIELDS = ("thicken",)
"""JobSpec's fields that older servers did not write: job.json holds them only when set, so that an older
job's file reads and writes back the same."""


def spec_json(spec: JobSpec) -> dict:
    """The spec as job.json holds it."""
    return {k: v for k, v in asdict(spec).items() if not (k in LATER_FIELDS and v is None)}


def spec_from_json(doc: dict) -> JobSpec:
    """The spec of a job.json; keys it does not know (a newer server's) are left out, so the job still
    loads."""
    known = set(JobSpec.__dataclass_fields__)
    return JobSpec(**{k: v for k, v in doc.items() if k in known})
