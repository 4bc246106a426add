"""Assembly files: the project's `assembly.json` and DESIA's `.puz`.

`assembly.json` (format "rllock-assembly", version 1):
  format, version      "rllock-assembly", 1
  shape                the input shape's name or file
  dimensions           [X, Y, Z] of the label grid
  labels               X*Y*Z ints, x fastest, then y, then z (index x + X*(y + Y*z)), as in `.puz`:
                       0 empty, 1..K the piece id = disassembly order
  K, n, N              piece count, size of P1..P(K-1) (floor(N/K)), voxel count
  key                  1 (the key is always the first piece out)
  removal              "straight" or "path"
  disassembly          [{"piece": i, "moves": [{"direction": "+x", "steps": s}, ...]}] for i = 1..K-1,
                       each piece's moves out of the remaining pieces' bounding box, in order; piece K stays
  method               {"name": ..., settings}
  seed                 the seed that produced it
  timings              {"seconds": time spent finding this assembly, ...}
  verification         the verifier's verdict: {"valid": true, "checker": ..., "checker_version": ...,
                       "removal": ..., "piece_sizes": [...], "verified_at": ISO time}

Nothing is written unless the verifier passes it; `assembly.puz` ends with a comment line saying so.
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from rllock.core.shapes import from_xfastest, read_puz_labels, to_xfastest, write_puz
from rllock.core.verifier import CHECKER_NAME, CHECKER_VERSION, Verdict, validate_labels, verify_labels
from rllock.errors import RLLockError

FORMAT = "rllock-assembly"

# Draws a picture of an assembly next to it: (labels grid, verdict, output folder). Passed in by callers
# that want pictures (`rllock.files.render.write_picture`), so this module needs no plotting library.
PictureWriter = Callable[[np.ndarray, Verdict, Path], None]


def read_assembly(path: str | Path) -> tuple[np.ndarray, dict]:
    """(labels grid [x, y, z], metadata) of a `.puz` or `assembly.json` file (or a folder holding one)."""
    path = Path(path)
    if path.is_dir():
        path = path / "assembly.json"
    if not path.is_file():
        raise RLLockError(f"no such file: {path}")
    if path.suffix.lower() == ".puz":
        return read_puz_labels(path), {}
    if path.suffix.lower() != ".json":
        raise RLLockError(f"unsupported assembly file {path}: use .puz or the project's assembly.json")
    try:
        data = json.loads(path.read_text())
        if data.get("format") != FORMAT:
            raise RLLockError(f"malformed assembly file {path}: not an {FORMAT} file")
        dims = tuple(int(d) for d in data["dimensions"])
        if not all(isinstance(v, int) and not isinstance(v, bool) for v in data["labels"]):
            raise RLLockError(f"malformed assembly file {path}: labels must be integers")
        labels = np.asarray(data["labels"], dtype=np.int64)
        if len(dims) != 3 or min(dims) < 1 or labels.size != dims[0] * dims[1] * dims[2]:
            raise RLLockError(f"malformed assembly file {path}: labels do not match dimensions {dims}")
        counts = tuple(data[key] for key in ("K", "n", "N"))
        if not all(isinstance(v, int) and not isinstance(v, bool) for v in counts):
            raise RLLockError(f"malformed assembly file {path}: K, n and N must be integers")
    except (json.JSONDecodeError, KeyError, TypeError, ValueError, AttributeError) as exc:
        raise RLLockError(f"malformed assembly file {path}: {exc}") from None
    grid = from_xfastest(labels, dims)  # type: ignore[arg-type]
    _check_counts(path, grid, *counts)
    return grid, data


def _check_counts(path: Path, labels: np.ndarray, k: int, n: int, total: int) -> None:
    """An assembly.json's labels against its own K, n and N and the rule that P1..P(K-1) have
    n = floor(N/K) voxels each: a label changed by hand would otherwise be verified as another assembly."""
    try:
        validate_labels(labels, pieces=k)
    except RLLockError as exc:
        raise RLLockError(f"assembly file {path}: {exc}") from None
    filled = int(np.count_nonzero(labels))
    if filled != total:
        raise RLLockError(f"assembly file {path} says N = {total}, but its labels fill {filled} voxels")
    if n != total // k:
        raise RLLockError(
            f"assembly file {path} says n = {n}, but floor(N/K) = floor({total}/{k}) = {total // k}"
        )
    sizes = np.bincount(labels.ravel(), minlength=k + 1)
    for piece in range(1, k):
        if sizes[piece] != n:
            raise RLLockError(
                f"assembly file {path}: piece {piece} has {sizes[piece]} voxels, not n = {n} "
                f"(P1..P(K-1) have n = floor(N/K) voxels each)"
            )


def _publish(staging: Path, out: Path) -> None:
    """Move a finished folder into place, so that an interrupted write never leaves a folder of that name
    half written; an earlier folder of the name (a run's best assembly) is replaced whole."""
    if out.exists():
        old = out.parent / f".{out.name}.old"
        shutil.rmtree(old, ignore_errors=True)
        out.rename(old)
        staging.rename(out)
        shutil.rmtree(old)
    else:
        staging.rename(out)


def write_assembly(
    out_dir: str | Path,
    labels: np.ndarray,
    *,
    removal: str,
    shape: str,
    method: dict,
    seed: int,
    timings: dict,
    picture: PictureWriter | None = None,
) -> dict:
    """Verify `labels` and, only if valid, write assembly.json and assembly.puz into `out_dir`, and the
    picture when a `picture` writer is given. The files are written into a hidden sibling folder first
    and that folder is renamed to `out_dir` when all are written.

    Returns the JSON document. An invalid assembly here is a bug upstream, so it raises.
    """
    verdict = verify_labels(labels, removal)
    if not verdict.valid:
        raise AssertionError(
            f"refusing to write an invalid assembly (stage {verdict.failed_stage}: {verdict.failed_check})"
        )
    out = Path(out_dir)
    staging = out.parent / f".{out.name}.partial"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    n_voxels = int((labels != 0).sum())
    doc = {
        "format": FORMAT,
        "version": 1,
        "shape": shape,
        "dimensions": list(labels.shape),
        "labels": [int(v) for v in to_xfastest(labels)],
        "K": verdict.pieces,
        "n": n_voxels // verdict.pieces,
        "N": n_voxels,
        "key": 1,
        "removal": removal,
        "disassembly": verdict.disassembly,
        "method": method,
        "seed": seed,
        "timings": timings,
        "verification": {
            "valid": True,
            "checker": CHECKER_NAME,
            "checker_version": CHECKER_VERSION,
            "removal": removal,
            "piece_sizes": verdict.piece_sizes,
            "verified_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        },
    }
    try:
        (staging / "assembly.json").write_text(json.dumps(doc, indent=1))
        write_puz(staging / "assembly.puz", labels)
        with open(staging / "assembly.puz", "a") as fh:
            fh.write(f"# verified valid by {CHECKER_NAME} v{CHECKER_VERSION}, removal={removal}\n")
        if picture is not None:
            picture(labels, verdict, staging)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    _publish(staging, out)
    return doc
