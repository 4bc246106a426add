"""Voxel shapes: built-in names, the DESIA `.puz`, High-Level `.vol` and `.npy` file formats, and
mesh files of the common formats (voxelized by `rllock.core.meshes`).

Built-in names are generated shapes (`cubeN`, `box:WxHxD`, `ring`) and the published shapes vendored in
`rllock/data/shapes/` (`sofa`, `desia-bunny`, ...; sources and licences in `rllock/data/README.md`), so a
name works from any directory. `data_path` finds any vendored file.

Every grid in RL-Lock is a numpy array indexed `[x, y, z]`. The text formats store x fastest, then y,
then z, which is numpy's C order of an array indexed `[z, y, x]`; `from_xfastest` and `to_xfastest`
are the only places that know this.
"""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

import numpy as np

from rllock.core import reference_checkers as reference
from rllock.errors import RLLockError

# Published shapes shipped with the package: name -> file under rllock/data/shapes/.
VENDORED_SHAPES = {
    "bunny": "highlevel_Bunny_11x10x8.vol",
    "cubeweird": "highlevel_CubeWeird_6x6x6.vol",
    "mario": "highlevel_Mario_12x16x4.vol",
    "shelf": "highlevel_Shelf_9x9x4.vol",
    "sofa": "highlevel_Sofa_7x8x6.vol",
    "spider": "highlevel_Spider_12x13x6.vol",
    "desia-cube4": "desia_Cube_4x4x4_origin.puz",
    "desia-cube5": "desia_Cube_5x5x5_origin.puz",
    "desia-hollow-cube4": "desia_Cube_hollow_4x4x4_origin.puz",
    "desia-bunny": "desia_bunny_origin.puz",
    "desia-dog": "desia_dog_origin.puz",
}
BUILTIN_HELP = "cubeN (e.g. cube4), box:WxHxD (e.g. box:4x3x2), ring, stairs, tube, " + ", ".join(
    VENDORED_SHAPES
)

MESH_SUFFIXES = (".stl", ".obj", ".ply", ".off", ".glb", ".gltf", ".3mf")
"""The mesh files a shape may come from (`rllock.core.mesh_files` reads them)."""
MESH_FORMATS = ", ".join(s.lstrip(".").upper() for s in MESH_SUFFIXES)

_DATA = Path(__file__).resolve().parents[1] / "data"


def data_path(relative: str | Path) -> Path:
    """The path of a file (or folder) vendored under `rllock/data/`, e.g. "published/Cube_4x4x4_K9.puz"."""
    return _DATA / relative


def cube(size: int) -> np.ndarray:
    return np.ones((size, size, size), dtype=bool)


def ring() -> np.ndarray:
    """The paper's ring: an 8x8 square, 3 layers thick, with a centred 4x4 hole (N = 144)."""
    grid = np.ones((8, 8, 3), dtype=bool)
    grid[2:6, 2:6, :] = False
    return grid


def stairs() -> np.ndarray:
    """Three steps, 6 voxels wide: columns of height 6, 4 and 2, each 2 deep (N = 144)."""
    grid = np.zeros((6, 6, 6), dtype=bool)
    for x in range(6):
        grid[x, :, : 6 - 2 * (x // 2)] = True
    return grid


def tube() -> np.ndarray:
    """A square tube: 7x7, 4 long, with a centred 3x3 hole through it (N = 160)."""
    grid = np.ones((7, 7, 4), dtype=bool)
    grid[2:5, 2:5, :] = False
    return grid


def grid_sha256(grid: np.ndarray) -> str:
    """A shape's fingerprint: what checkpoints record to know the shape they were trained on."""
    return hashlib.sha256(np.ascontiguousarray(grid).tobytes() + bytes(str(grid.shape), "ascii")).hexdigest()


def builtin_shape(name: str) -> np.ndarray | None:
    """The grid of a built-in shape name, or None when `name` is not one."""
    if match := re.fullmatch(r"cube(\d+)", name):
        size = int(match.group(1))
        if size < 1:
            raise RLLockError(f"cube size must be at least 1, got {name!r}")
        return cube(size)
    if match := re.fullmatch(r"box:(\d+)x(\d+)x(\d+)", name):
        dims = tuple(int(g) for g in match.groups())
        if min(dims) < 1:
            raise RLLockError(f"box dimensions must be at least 1, got {name!r}")
        return np.ones(dims, dtype=bool)
    if name == "ring":
        return ring()
    if name == "stairs":
        return stairs()
    if name == "tube":
        return tube()
    if name in VENDORED_SHAPES:
        path = data_path(Path("shapes") / VENDORED_SHAPES[name])
        return read_vol(path) if path.suffix == ".vol" else read_puz_labels(path) != 0
    return None


def from_xfastest(values: np.ndarray, dims: tuple[int, int, int]) -> np.ndarray:
    nx, ny, nz = dims
    return values.reshape(nz, ny, nx).transpose(2, 1, 0).copy()


def to_xfastest(grid: np.ndarray) -> np.ndarray:
    return grid.transpose(2, 1, 0).reshape(-1)


def _parse_ints(path: Path, tokens: list[str], what: str) -> list[int]:
    try:
        return [int(t) for t in tokens]
    except ValueError:
        raise RLLockError(f"malformed {what} file {path}: expected integers") from None


def _read_text(path: Path) -> list[str]:
    if not path.is_file():
        raise RLLockError(f"no such file: {path}")
    try:
        # '#' starts a comment to the end of the line (RL-Lock writes how a file was verified that way).
        return [tok for line in path.read_text().splitlines() for tok in line.split("#", 1)[0].split()]
    except (UnicodeDecodeError, OSError) as exc:
        raise RLLockError(f"cannot read {path}: {exc}") from None


def _dims(path: Path, tokens: list[str], what: str) -> tuple[int, int, int]:
    if len(tokens) < 3:
        raise RLLockError(f"malformed {what} file {path}: missing the 'NX NY NZ' header")
    dims = tuple(_parse_ints(path, tokens[:3], what))
    if min(dims) < 1:
        raise RLLockError(f"malformed {what} file {path}: dimensions must be positive, got {dims}")
    return dims  # type: ignore[return-value]


def read_puz_labels(path: str | Path) -> np.ndarray:
    """A DESIA `.puz` file as an int grid `[x, y, z]`: 0 empty, otherwise the 1-based piece id."""
    path = Path(path)
    tokens = _read_text(path)
    dims = _dims(path, tokens, ".puz")
    count = dims[0] * dims[1] * dims[2]
    values = _parse_ints(path, tokens[3:], ".puz")
    if len(values) != count:
        raise RLLockError(
            f"malformed .puz file {path}: header says {count} voxels, found {len(values)} values"
        )
    labels = np.asarray(values, dtype=np.int64)
    if labels.min() < 0:
        raise RLLockError(f"malformed .puz file {path}: negative voxel value")
    return from_xfastest(labels, dims)


def write_puz(path: str | Path, labels: np.ndarray) -> None:
    """Write an int grid `[x, y, z]` in DESIA's `.puz` layout (one y-row a line, blank line between z)."""
    nx, ny, nz = labels.shape
    lines = [f"{nx} {ny} {nz}"]
    for z in range(nz):
        for y in range(ny):
            lines.append(" ".join(str(int(labels[x, y, z])) for x in range(nx)) + " ")
        lines.append("")
    Path(path).write_text("\n".join(lines) + "\n")


def read_vol(path: str | Path) -> np.ndarray:
    """A High-Level `.vol` file: `NX NY NZ`, a voxel-size line (ignored), then 0/1 values x fastest."""
    path = Path(path)
    tokens = _read_text(path)
    dims = _dims(path, tokens, ".vol")
    count = dims[0] * dims[1] * dims[2]
    if len(tokens) < 6:
        raise RLLockError(f"malformed .vol file {path}: missing the voxel-size line")
    try:
        [float(t) for t in tokens[3:6]]
    except ValueError:
        raise RLLockError(f"malformed .vol file {path}: voxel size must be three numbers") from None
    values = _parse_ints(path, tokens[6:], ".vol")
    if len(values) != count:
        raise RLLockError(
            f"malformed .vol file {path}: header says {count} voxels, found {len(values)} values"
        )
    return from_xfastest(np.asarray(values) != 0, dims)


def read_npy(path: str | Path) -> np.ndarray:
    path = Path(path)
    if not path.is_file():
        raise RLLockError(f"no such file: {path}")
    try:
        grid = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise RLLockError(f"malformed .npy file {path}: {exc}") from None
    if grid.ndim != 3 or not (grid.dtype == bool or np.issubdtype(grid.dtype, np.integer)):
        raise RLLockError(
            f"malformed .npy file {path}: expected a 3-D boolean array, got {grid.dtype} {grid.shape}"
        )
    return grid != 0


def crop(grid: np.ndarray) -> np.ndarray:
    """The grid cut down to the bounding box of its filled voxels."""
    filled = np.argwhere(grid)
    lo, hi = filled.min(axis=0), filled.max(axis=0) + 1
    return grid[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]].copy()


def is_connected(grid: np.ndarray) -> bool:
    """Whether the filled voxels of a boolean grid form one 6-connected solid."""
    return reference.is_connected(reference.voxel(v) for v in np.argwhere(grid))


def validate_shape(grid: np.ndarray, name: str) -> np.ndarray:
    if not grid.any():
        raise RLLockError(f"shape {name!r} is empty")
    grid = crop(grid)
    if not is_connected(grid):
        raise RLLockError(f"shape {name!r} is not 6-connected: it must be one solid piece")
    return grid


def load_shape(spec: str, resolution: int | None = None) -> np.ndarray:
    """The boolean grid `[x, y, z]` named by `spec`: a built-in name, a .puz/.vol/.npy file, or a mesh
    file (MESH_SUFFIXES) voxelized to at most `resolution` voxels along its longest side (see
    rllock.core.meshes).

    The result is cropped to its bounding box, non-empty and 6-connected.
    """
    path = Path(spec)
    suffix = path.suffix.lower()
    is_mesh = suffix in MESH_SUFFIXES
    if resolution is not None and not is_mesh:
        raise RLLockError(f"a resolution applies only to meshes ({MESH_FORMATS}), not to {spec!r}")
    grid = builtin_shape(spec)
    if grid is None:
        if is_mesh:
            # Imported here because trimesh is slow to import and only mesh input needs it.
            from rllock.core.meshes import voxelize_mesh

            grid = voxelize_mesh(path, resolution)
        elif suffix == ".puz":
            grid = read_puz_labels(path) != 0
        elif suffix == ".vol":
            grid = read_vol(path)
        elif suffix == ".npy":
            grid = read_npy(path)
        elif path.exists():
            raise RLLockError(
                f"unsupported shape file {spec!r}: use .puz, .vol, .npy or a mesh ({MESH_FORMATS})"
            )
        else:
            raise RLLockError(f"unknown shape {spec!r}: not a file, and not a built-in ({BUILTIN_HELP})")
    return validate_shape(grid, spec)


def piece_size(n_voxels: int, pieces: int) -> int:
    """n = floor(N / K), after checking that K makes sense for N voxels."""
    if pieces < 2:
        raise RLLockError(f"the piece count K must be at least 2, got {pieces}")
    if pieces > n_voxels:
        raise RLLockError(f"K = {pieces} is larger than the shape's {n_voxels} voxels (n = N/K < 1)")
    return n_voxels // pieces
