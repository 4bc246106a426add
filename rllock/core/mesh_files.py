"""Triangles from the mesh files people have: STL, OBJ, PLY (ASCII or binary, faces or triangle strips),
OFF, glTF/GLB and 3MF. trimesh reads all but two cases: a PLY whose surface is stored as triangle strips (the
form of several scanning repositories), which trimesh returns as bare points, and 3MF, whose trimesh reader
needs two more packages; both are read here. Cleaning and voxelizing the triangles is `rllock.core.meshes`.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
import zipfile
from pathlib import Path

import numpy as np
import trimesh

from rllock.errors import RLLockError

Triangles = tuple[np.ndarray, np.ndarray]
"""(vertices float [V, 3], faces int [F, 3])."""

_CORE = "{http://schemas.microsoft.com/3dmanufacturing/core/2015/02}"
_PRODUCTION = "{http://schemas.microsoft.com/3dmanufacturing/production/2015/06}"
_ROOT_MODEL = "3D/3dmodel.model"
MAX_3MF_BYTES = 1 << 30
"""A 3MF package that unpacks to more than this is refused before it is read (a zip of a few kilobytes can
unpack to gigabytes)."""


def read_triangles(path: Path) -> Triangles:
    """The triangles of the mesh file at `path`, every object of it in its placed position; a one-line
    error for a file that cannot be read or holds no surface (a point cloud, an empty scene)."""
    if not path.is_file():
        raise RLLockError(f"no such file: {path}")
    try:
        if path.suffix.lower() == ".3mf":
            vertices, faces = _read_3mf(path)
        else:
            vertices, faces = _read_with_trimesh(path)
    except RLLockError:
        raise
    # trimesh's many loaders (and zip and XML parsers) fail on malformed files with unrelated exceptions.
    except Exception as exc:
        raise RLLockError(f"cannot read mesh {path}: {exc}") from None
    if len(faces) == 0:
        if len(vertices):
            raise RLLockError(
                f"{path} holds {len(vertices)} points but no surface (a point cloud): mesh it first, "
                "for example by Poisson reconstruction in MeshLab or CloudCompare"
            )
        raise RLLockError(f"{path} holds no triangle mesh")
    return vertices, faces


def _read_with_trimesh(path: Path) -> Triangles:
    loaded = trimesh.load(path)
    if isinstance(loaded, trimesh.Scene):  # glTF, and OBJ files of several objects: placed, then joined
        meshes = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh) and len(g.faces)]
        loaded = trimesh.util.concatenate(meshes) if meshes else trimesh.Trimesh()
    if isinstance(loaded, trimesh.Trimesh) and len(loaded.faces):
        return np.asarray(loaded.vertices, np.float64), np.asarray(loaded.faces, np.int64)
    # Bare points: a point cloud, or a PLY file whose surface trimesh did not read (triangle strips).
    points = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), np.float64).reshape(-1, 3)
    return points, strip_faces(loaded.metadata.get("_ply_raw", {}))


def strip_faces(elements: dict) -> np.ndarray:
    """The triangles of a PLY file's `tristrips` element (as trimesh parses it): each row a sequence of
    vertex indices, -1 between strips; triangle i of a strip is (s[i], s[i+1], s[i+2]), every second one
    turned over to keep the strip's winding; degenerate ones (a repeated index, which joins strips) are
    left out."""
    element = elements.get("tristrips")
    if not element or not element.get("length"):
        return np.zeros((0, 3), np.int64)
    data = element["data"]
    rows = data["vertex_indices"]
    if getattr(rows, "dtype", None) is not None and rows.dtype.names:  # binary: (count, list) records
        rows = rows[rows.dtype.names[-1]]
    faces = []
    for row in rows:
        sequence = np.asarray(row, np.int64).ravel()
        for strip in np.split(sequence, np.flatnonzero(sequence < 0)):
            strip = strip[strip >= 0]
            if len(strip) < 3:
                continue
            a, b, c = strip[:-2], strip[1:-1], strip[2:]
            odd = np.arange(len(a)) % 2 == 1
            tri = np.column_stack([np.where(odd, b, a), np.where(odd, a, b), c])
            keep = (tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 0] != tri[:, 2])
            faces.append(tri[keep])
    return np.concatenate(faces) if faces else np.zeros((0, 3), np.int64)


def _read_3mf(path: Path) -> Triangles:
    """Every build item of a 3MF file, its objects' meshes and components (also those in other model
    files of the package, the production extension's p:path) moved by their transforms."""
    with zipfile.ZipFile(path) as package:
        unpacked = sum(info.file_size for info in package.infolist())
        if unpacked > MAX_3MF_BYTES:
            raise RLLockError(f"{path} unpacks to {unpacked / 2**20:.0f} MiB, more than a 3MF model needs")
        names = {n.lstrip("/").lower(): n for n in package.namelist()}
        models: dict[str, ET.Element] = {}

        def model(part: str) -> ET.Element:
            key = part.lstrip("/").lower()
            if key not in models:
                if key not in names:
                    raise RLLockError(f"cannot read mesh {path}: it names a part {part!r} it does not hold")
                models[key] = ET.fromstring(package.read(names[key]))
            return models[key]

        vertices: list[np.ndarray] = []
        faces: list[np.ndarray] = []
        count = 0

        def place(part: str, object_id: str, transform: np.ndarray, depth: int) -> None:
            nonlocal count
            if depth > 32:
                raise RLLockError(f"cannot read mesh {path}: its components refer to each other in a loop")
            found = model(part).find(f"{_CORE}resources/{_CORE}object[@id='{object_id}']")
            if found is None:
                raise RLLockError(f"cannot read mesh {path}: it names an object {object_id} it does not hold")
            mesh = found.find(f"{_CORE}mesh")
            if mesh is not None:
                points = np.array(
                    [[float(v.get(a, "0")) for a in "xyz"] for v in mesh.iter(f"{_CORE}vertex")], float
                ).reshape(-1, 3)
                tris = np.array(
                    [[int(t.get(a, "0")) for a in ("v1", "v2", "v3")] for t in mesh.iter(f"{_CORE}triangle")],
                    np.int64,
                ).reshape(-1, 3)
                vertices.append(points @ transform[:3, :3].T + transform[:3, 3])
                faces.append(tris + count)
                count += len(points)
            for component in found.iter(f"{_CORE}component"):
                inner = component.get(f"{_PRODUCTION}path") or part
                place(inner, component.get("objectid", ""), transform @ _matrix(component), depth + 1)

        build = model(_ROOT_MODEL).find(f"{_CORE}build")
        for item in [] if build is None else build.iter(f"{_CORE}item"):
            part = item.get(f"{_PRODUCTION}path") or _ROOT_MODEL
            place(part, item.get("objectid", ""), _matrix(item), 0)
    if not faces:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    return np.concatenate(vertices), np.concatenate(faces)


def _matrix(element: ET.Element) -> np.ndarray:
    """A 3MF transform attribute ("m00 m01 m02 m10 ... m32": rows of a 4x3 matrix that acts on row
    vectors) as a 4x4 matrix acting on column vectors; the identity when there is none."""
    values = [float(v) for v in element.get("transform", "").split()]
    out = np.eye(4)
    if values:
        if len(values) != 12:
            raise RLLockError(f"a 3MF transform has 12 numbers, not {len(values)}")
        out[:3, :3] = np.array(values[:9]).reshape(3, 3).T
        out[:3, 3] = values[9:]
    return out
