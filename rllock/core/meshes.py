"""Triangle meshes both ways: voxel pieces to watertight meshes, and `.stl`/`.obj` models to voxel shapes.

Pieces to meshes. A piece is the union of its unit voxels, built with manifold3d's exact booleans and then
simplified so that coplanar faces are merged. With a clearance `gap`, the piece is eroded by gap/2 (an
inward offset of every face that borders another piece or the outside), so two neighbouring pieces end
up `gap` apart and the whole assembly `gap` smaller along each axis; faces between voxels of the same
piece stay fused. The eroded solid is the union of a few boxes per voxel: the voxel's core, plus a
bridge towards every neighbouring voxel, every full 2x2 square and every full 2x2x2 cube it belongs to.

Volume, exactly (`piece_volume`): with s the voxel size and r = gap/2, space splits into voxel interiors
(s-2r)^3, slabs (2r)(s-2r)^2 across the faces between voxels, prisms (2r)^2(s-2r) along their edges and
cubes (2r)^3 around their corners; the eroded piece holds exactly those whose surrounding voxels all
belong to it. So its volume is N (s-2r)^3 + F 2r (s-2r)^2 + Q (2r)^2 (s-2r) + C (2r)^3, with N its voxels,
F its face-neighbouring voxel pairs, Q its full 2x2 squares and C its full 2x2x2 cubes: N s^3 at gap 0.

Printing, and why the export's default gap is not 0. Two voxels of one piece may touch only along an
edge (the two voxels beside that edge belong to other pieces or the outside). At gap 0 the mesh keeps the
two sheets that meet there topologically apart, so it is a closed 2-manifold, and stays one in OBJ, which
keeps vertex indices. STL has no shared vertices: slicers (and trimesh) weld them by position, and then
the sheets meet on that edge: four faces on one edge, or, where the sheets were triangulated differently,
surfaces that touch along it without sharing mesh edges (passing an edge count, still not a 2-manifold).
Any gap > 0 removes such contacts: every face beside the edge borders another piece or the outside, so it
moves in by gap/2, and the two voxels end up `gap` apart along both axes across the edge (corner-only
contacts separate the same way). So `rllock export` defaults to a gap of 0.2 mm
(`rllock.files.export.PRINT_GAP`),
a typical FDM printing clearance: every piece's STL is watertight as slicers
read it, and printed pieces fit together. The functions here default to gap 0, the exact geometry;
`edge_only_contacts` counts the contacts that make a gap-0 STL non-manifold.

Meshes to voxels. A closed mesh is sampled at voxel centres on a grid whose longest side has
`resolution` voxels, mesh axes kept; a voxel is filled when its centre is inside the solid, tested layer
by layer against the solid's cross-section at that height. Only the largest 6-connected part is kept,
with a warning; when that drops more than MAX_DROPPED of the voxels the mesh is refused, naming a higher
resolution that keeps its parts together where one up to twice the given one does.
"""

from __future__ import annotations

import itertools
import logging
from pathlib import Path

import manifold3d as m3
import numpy as np
import trimesh
from matplotlib.path import Path as MplPath
from scipy import ndimage

from rllock.errors import RLLockError

DEFAULT_RESOLUTION = 8
# The share of a mesh's voxels that may be dropped (parts that touch the rest only along an edge or not at
# all) before the shape is too far from the model to search.
MAX_DROPPED = 0.25

log = logging.getLogger(__name__)


def _boxes(cells: np.ndarray, inset: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """(lo, hi) corners, in voxel units, of boxes whose union is the piece eroded by `inset` (< 0.5)."""
    filled = {tuple(int(c) for c in v) for v in cells}
    # Without an inset the unit voxels alone are the solid; bridges only matter when faces move in.
    offsets = [(0, 0, 0)] if inset == 0 else list(itertools.product((0, 1), repeat=3))
    boxes = []
    for v in filled:
        for off in offsets:
            block = itertools.product(*[range(v[a], v[a] + 1 + off[a]) for a in range(3)])
            if all(b in filled for b in block):
                lo = np.asarray(v, dtype=float) + inset
                hi = np.asarray(v, dtype=float) + 1 - inset + np.asarray(off)
                boxes.append((lo, hi))
    return boxes


def _blocks(cells: np.ndarray) -> dict[tuple[int, int, int], int]:
    """For each block shape (1 or 2 voxels along each axis), how many such blocks the piece fills."""
    filled = {tuple(int(c) for c in v) for v in cells}
    counts: dict[tuple[int, int, int], int] = {}
    for ox, oy, oz in itertools.product((0, 1), repeat=3):
        deltas = list(itertools.product(range(ox + 1), range(oy + 1), range(oz + 1)))
        counts[ox, oy, oz] = sum(
            all((v[0] + dx, v[1] + dy, v[2] + dz) in filled for dx, dy, dz in deltas) for v in filled
        )
    return counts


def piece_volume(cells: np.ndarray, voxel_size: float = 10.0, gap: float = 0.0) -> float:
    """The exact volume of `piece_mesh(cells, voxel_size, gap)` (the module docstring derives it)."""
    r = gap / 2
    inner, across = voxel_size - 2 * r, 2 * r
    return float(sum(n * inner ** (3 - sum(off)) * across ** sum(off) for off, n in _blocks(cells).items()))


def edge_only_contacts(cells: np.ndarray) -> int:
    """How many pairs of the piece's voxels touch along an edge and nowhere else (neither voxel beside
    that edge is in the piece): at gap 0 each is a non-manifold edge once STL vertices are welded."""
    filled = {tuple(int(c) for c in v) for v in cells}
    count = 0
    for v in filled:
        for a, b in itertools.combinations(range(3), 2):
            for sign in (1, -1):  # +1 along a and either way along b: each pair once
                step_a, step_b = [0, 0, 0], [0, 0, 0]
                step_a[a], step_b[b] = 1, sign
                beside_a = tuple(v[i] + step_a[i] for i in range(3))
                beside_b = tuple(v[i] + step_b[i] for i in range(3))
                across = tuple(v[i] + step_a[i] + step_b[i] for i in range(3))
                count += across in filled and beside_a not in filled and beside_b not in filled
    return count


def piece_mesh(cells: np.ndarray, voxel_size: float = 10.0, gap: float = 0.0) -> trimesh.Trimesh:
    """The watertight mesh of one piece, given as the (n, 3) voxel coordinates it occupies, in the
    assembled position (voxel (x, y, z) spans [x, x+1] * voxel_size along x, and so on), eroded by gap/2
    where it borders other pieces or the outside."""
    if voxel_size <= 0:
        raise RLLockError(f"the voxel size must be positive, got {voxel_size}")
    if not 0 <= gap < voxel_size:
        raise RLLockError(
            f"the gap must be at least 0 and smaller than the voxel size {voxel_size}, got {gap}"
        )
    if len(cells) == 0:
        raise RLLockError("cannot mesh a piece with no voxels")
    inset = gap / 2 / voxel_size
    cubes = [
        m3.Manifold.cube((hi - lo) * voxel_size).translate(lo * voxel_size) for lo, hi in _boxes(cells, inset)
    ]
    # as_original() forgets which input cube each triangle came from, so that simplify() may merge
    # coplanar triangles across cubes; the tiny tolerance keeps the geometry exact.
    solid = m3.Manifold.batch_boolean(cubes, m3.OpType.Add).as_original().simplify(1e-9)
    mesh = solid.to_mesh()
    return trimesh.Trimesh(np.asarray(mesh.vert_properties)[:, :3], np.asarray(mesh.tri_verts), process=False)


def assembly_meshes(labels: np.ndarray, voxel_size: float = 10.0, gap: float = 0.0) -> list[trimesh.Trimesh]:
    """One mesh per piece 1..K of a label grid [x, y, z], in piece order."""
    return [piece_mesh(np.argwhere(labels == k), voxel_size, gap) for k in range(1, int(labels.max()) + 1)]


def _load_mesh(path: Path) -> trimesh.Trimesh:
    if not path.is_file():
        raise RLLockError(f"no such file: {path}")
    try:
        mesh = trimesh.load(path, force="mesh")
    # trimesh's many loaders fail on malformed files with unrelated exception types.
    except Exception as exc:
        raise RLLockError(f"cannot read mesh {path}: {exc}") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise RLLockError(f"{path} holds no triangle mesh")
    if not mesh.is_watertight:
        raise RLLockError(f"mesh {path} is not watertight: filling its inside needs a closed surface")
    return mesh


def _solid(mesh: trimesh.Trimesh, path: Path) -> m3.Manifold:
    solid = m3.Manifold(
        m3.Mesh(
            vert_properties=np.asarray(mesh.vertices, dtype=np.float32),
            tri_verts=np.asarray(mesh.faces, dtype=np.uint32),
        )
    )
    if solid.status() != m3.Error.NoError:
        raise RLLockError(f"mesh {path} is not a closed manifold surface ({solid.status().name})")
    return solid


def _sample_inside(solid: m3.Manifold, resolution: int) -> np.ndarray:
    """Boolean grid [x, y, z]: voxel centres inside the solid, `resolution` voxels along its longest side.

    Each layer of centres is tested against the solid's cross-section at that height (even-odd over its
    contours): fast and robust, where casting a ray per point is slow on meshes of many triangles.
    """
    box = np.asarray(solid.bounding_box(), dtype=float)
    lo, hi = box[:3], box[3:]
    extent = hi - lo
    pitch = float(extent.max()) / resolution
    if pitch <= 0:
        raise RLLockError("the mesh has no volume")
    # The tolerance keeps an exact multiple of the pitch from gaining a voxel to rounding.
    dims = np.maximum(1, np.ceil(extent / pitch - 1e-6)).astype(int)
    origin = (lo + hi) / 2 - dims * pitch / 2
    # A tiny irrational nudge keeps sample points off faces that lie exactly halfway between grid planes,
    # where inside and outside would be a tie.
    centres = [
        origin[a] + (np.arange(dims[a]) + 0.5 + 1e-4 * np.sqrt((2, 3, 5)[a])) * pitch for a in range(3)
    ]
    points = np.stack(np.meshgrid(centres[0], centres[1], indexing="ij"), axis=-1).reshape(-1, 2)
    grid = np.zeros(tuple(dims), dtype=bool)
    for iz, z in enumerate(centres[2]):
        inside = np.zeros(len(points), dtype=bool)
        for contour in solid.slice(z).to_polygons():
            inside ^= MplPath(contour).contains_points(points)
        grid[:, :, iz] = inside.reshape(dims[0], dims[1])
    return grid


def largest_component(grid: np.ndarray, name: str) -> np.ndarray:
    """The largest 6-connected part of a boolean grid, with a warning when voxels are dropped."""
    parts, count = ndimage.label(grid)  # the default structure is 6-connectivity
    if count <= 1:
        return grid
    sizes = np.bincount(parts.ravel())[1:]
    keep = parts == int(np.argmax(sizes)) + 1
    log.warning(
        "%s: kept the largest of %d connected parts, dropped %d of %d voxels",
        name,
        count,
        int(grid.sum() - keep.sum()),
        int(grid.sum()),
    )
    return keep


def voxelize_mesh(path: str | Path, resolution: int | None = None) -> np.ndarray:
    """A closed `.stl`/`.obj` mesh as a boolean grid [x, y, z] (mesh axes kept), at most `resolution`
    voxels along its longest side, reduced to its largest 6-connected part; refused when that part
    drops more than MAX_DROPPED of the voxels."""
    resolution = DEFAULT_RESOLUTION if resolution is None else resolution
    if resolution < 1:
        raise RLLockError(f"the resolution must be at least 1 voxel, got {resolution}")
    path = Path(path)
    solid = _solid(_load_mesh(path), path)
    grid = _sample_inside(solid, resolution)
    if not grid.any():
        raise RLLockError(f"mesh {path} fills no voxel at resolution {resolution}: try a higher resolution")
    kept = largest_component(grid, str(path))
    dropped, total = int(grid.sum() - kept.sum()), int(grid.sum())
    if dropped > MAX_DROPPED * total:
        raise RLLockError(
            f"mesh {path} at resolution {resolution} falls apart: its largest connected part keeps "
            f"{total - dropped} of {total} voxels; {_resolution_hint(solid, resolution)}"
        )
    return kept


def _resolution_hint(solid: m3.Manifold, resolution: int) -> str:
    """The lowest resolution above `resolution` (up to twice it) at which the largest part drops at most
    MAX_DROPPED of the voxels, as advice."""
    for higher in range(resolution + 1, 2 * resolution + 1):
        grid = _sample_inside(solid, higher)
        parts, count = ndimage.label(grid)
        if count and np.bincount(parts.ravel())[1:].max() >= (1 - MAX_DROPPED) * grid.sum():
            return f"--resolution {higher} keeps its parts together"
    return f"no resolution up to {2 * resolution} keeps them together (the model has separate parts)"
