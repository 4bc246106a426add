"""The files that cross the API besides a job's own: uploads, read no further than the server's cap, and
pieces.zip, the STL files of a done job's pieces for printing.
"""

from __future__ import annotations

import io
import math
import tempfile
import zipfile
from pathlib import Path

from fastapi import UploadFile

from rllock.errors import RLLockError
from rllock.orchestration.service.request import TooLarge, too_large

FORM_SLACK = 65536
"""Bytes a request body may carry beyond the upload cap: the form's other fields and its boundaries."""


def declared_too_large(content_length: str | None, cap: int) -> bool:
    """Whether a request's Content-Length says its body is larger than an upload of `cap` bytes can make
    it: such a body is refused before it is read, not after it was spooled to disk."""
    size = content_length or ""
    return size.isdigit() and int(size) > cap + FORM_SLACK


async def read_upload(file: UploadFile | None, cap: int) -> tuple[str, bytes] | None:
    """(the file's name as sent, its bytes), None when no file came; TooLarge past `cap` bytes, having
    read one byte more than the cap at most."""
    if file is None or not file.filename:
        return None
    data = await file.read(cap + 1)
    if len(data) > cap:
        raise TooLarge(too_large(cap))
    return file.filename, data


def check_print(voxel_size: float, gap: float) -> None:
    """A one-line error for print settings that make no pieces: the gap must leave some of each voxel."""
    if not (math.isfinite(voxel_size) and 0 < voxel_size <= 1000):
        raise RLLockError("voxel_size must be more than 0 and at most 1000 mm")
    if not (math.isfinite(gap) and 0 <= gap < voxel_size):
        raise RLLockError("gap must be at least 0 and smaller than voxel_size")


def zip_name(job_id: str, voxel_size: float, gap: float) -> str:
    """The download's name: the job and the settings it was made with."""
    return f"{job_id}-pieces-{voxel_size:g}mm-gap{gap:g}.zip"


def stl_zip(assembly: Path, voxel_size: float, gap: float) -> bytes:
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
            archive.writestr("README.txt", _readme(len(paths), meta, voxel_size, gap))
    return buffer.getvalue()


def _readme(pieces: int, meta: dict, voxel_size: float, gap: float) -> str:
    verification = meta.get("verification", {})
    return (
        f"{pieces} pieces of {meta.get('shape')} (K={meta.get('K')}, "
        f"removal={meta.get('removal')}), "
        f"{voxel_size:g} mm voxels, {gap:g} mm clearance between neighbouring pieces.\n"
        f"Piece 1 is the key; take the pieces out in order 1, 2, ... K.\n"
        f"The assembly was verified valid by {verification.get('checker')} "
        f"v{verification.get('checker_version')} at {verification.get('verified_at')}.\n"
    )
