"""Voxel pieces to watertight triangle meshes, for export (the other way, models to voxel shapes, is
`rllock.core.meshes`).

A piece is the union of its unit voxels, built with manifold3d's exact booleans and then
simplified so that coplanar faces are merged. With a clearance `gap`, the piece is eroded by gap/2 (an
inward offset of every face that borders another piece or the outside), so two neighbouring pieces end
up `gap` apart and the whole assembly `gap` smaller along each axis; faces between voxels of the same
piece stay fused. The eroded solid is a union of cells of a grid three times as fine (`_refined`): along
each axis a voxel splits into its core and a slab of width r = gap/2 at each end, and a cell is solid
when every voxel it touches belongs to the piece (a core its voxel; a slab, or an edge or a corner of
slabs, the two, four or eight voxels around it). Its surface, the faces between solid and empty cells,
is built directly, and manifold3d merges its coplanar faces: far cheaper than a boolean union of a box
per cell. Two solid cells never meet only along an edge or at a corner (where two voxels of a
piece do, r > 0 parts them), so the surface is a closed 2-manifold.

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
(`rllock.files.export.PRINT_GAP`), a typical FDM printing clearance: every piece's STL is watertight as
slicers read it, and printed pieces fit together. The functions here default to gap 0, the exact geometry;
`edge_only_contacts` counts the contacts that make a gap-0 STL non-manifold.
"""

from __future__ import annotations

import itertools
import multiprocessing as mp
import os
from concurrent.futures import ProcessPoolExecutor

import manifold3d as m3
import numpy as np
import trimesh

from rllock.core.verifier import label_cells
from rllock.errors import RLLockError


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
    _check_piece(cells, voxel_size, gap)
    return trimesh.Trimesh(*_piece_arrays(cells, voxel_size, gap), process=False)


def _check_piece(cells: np.ndarray, voxel_size: float, gap: float) -> None:
    if voxel_size <= 0:
        raise RLLockError(f"the voxel size must be positive, got {voxel_size}")
    if not 0 <= gap < voxel_size:
        raise RLLockError(
            f"the gap must be at least 0 and smaller than the voxel size {voxel_size}, got {gap}"
        )
    if len(cells) == 0:
        raise RLLockError("cannot mesh a piece with no voxels")


def _piece_arrays(cells: np.ndarray, voxel_size: float, gap: float) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, triangles) of `piece_mesh`, checked arguments assumed."""
    if gap == 0:
        # The unit voxels' union: manifold3d keeps voxels that meet only along an edge apart there.
        cubes = [m3.Manifold.cube([voxel_size] * 3).translate(v * voxel_size) for v in cells.astype(float)]
        solid = m3.Manifold.batch_boolean(cubes, m3.OpType.Add)
    else:
        vertices, triangles = _eroded_surface(cells, voxel_size, gap / 2)
        solid = m3.Manifold(
            m3.Mesh(vert_properties=vertices.astype(np.float32), tri_verts=triangles.astype(np.uint32))
        )
        if solid.status() != m3.Error.NoError:
            raise AssertionError(
                f"the eroded surface of a piece is not a closed 2-manifold: {solid.status()}"
            )
    # as_original() forgets which input each triangle came from, so that simplify() may merge coplanar
    # triangles; the tiny tolerance keeps the geometry exact.
    mesh = solid.as_original().simplify(1e-9).to_mesh()
    return np.asarray(mesh.vert_properties)[:, :3], np.asarray(mesh.tri_verts)


def _refined(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(solid cells of the grid three times as fine, bool [3X, 3Y, 3Z]; the voxel at its origin): per
    axis, fine cell 3x + 1 is voxel x's core, 3x + 2 and 3x + 3 the slabs on both sides of the face
    between voxels x and x + 1, solid when both are. Solid along every axis at once: the voxels a cell
    touches are the product of those it touches along each axis, so the axes refine one after another."""
    lo = cells.min(axis=0) - 1
    solid = np.zeros(cells.max(axis=0) - lo + 2, dtype=bool)
    solid[tuple((cells - lo).T)] = True
    for axis in range(3):
        coarse = np.moveaxis(solid, axis, 0)
        fine = np.zeros((3 * coarse.shape[0], *coarse.shape[1:]), dtype=bool)
        fine[1::3] = coarse
        both = coarse[:-1] & coarse[1:]
        fine[2:-1:3] = both
        fine[3::3] = both
        solid = np.moveaxis(fine, 0, axis)
    return solid, lo


def _eroded_surface(cells: np.ndarray, voxel_size: float, r: float) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, triangles) of the faces between the solid and the empty cells of `_refined`, wound
    outward, two triangles a face, vertices shared."""
    solid, lo = _refined(cells)
    planes = []  # per axis, the coordinate of each plane between fine cells
    for axis in range(3):
        x = (lo[axis] + np.arange(solid.shape[axis] // 3 + 1)).astype(float) * voxel_size
        planes.append(np.stack([x, x + r, x + voxel_size - r], axis=1).ravel()[: solid.shape[axis] + 1])
    quads = []
    for axis in range(3):
        u, w = [a for a in range(3) if a != axis]
        cells_along = np.moveaxis(solid, axis, 0)
        empty = np.zeros((1, *cells_along.shape[1:]), dtype=bool)
        padded = np.concatenate([empty, cells_along, empty])
        # (u, w) corners in this order wind around +axis for axis x and z, around -axis for y.
        handed = -1 if axis == 1 else 1
        for outward, faces in ((-1, padded[1:] & ~padded[:-1]), (1, padded[:-1] & ~padded[1:])):
            i, j, k = np.nonzero(faces)
            corners = np.empty((len(i), 4, 3), dtype=np.int64)
            corners[:, :, axis] = i[:, None]
            corners[:, :, u] = np.stack([j, j + 1, j + 1, j], axis=1)
            corners[:, :, w] = np.stack([k, k, k + 1, k + 1], axis=1)
            quads.append(corners if outward == handed else corners[:, ::-1])
    lattice, index = np.unique(np.concatenate(quads).reshape(-1, 3), axis=0, return_inverse=True)
    q = index.reshape(-1, 4)
    vertices = np.stack([planes[a][lattice[:, a]] for a in range(3)], axis=1)
    return vertices, np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])


# From this many pieces, `assembly_meshes` meshes them in a process per core: a piece meshes in a few
# milliseconds, so below it starting the processes costs more than they save.
PARALLEL_FROM = 300


def assembly_meshes(
    labels: np.ndarray, voxel_size: float = 10.0, gap: float = 0.0, workers: int | None = None
) -> list[trimesh.Trimesh]:
    """One mesh per piece 1..K of a label grid [x, y, z], in piece order, meshed by `workers` processes
    (None: one per core from PARALLEL_FROM pieces, else this process alone)."""
    k = int(labels.max())
    pieces = label_cells(labels, k)[1:]
    for p in pieces:
        _check_piece(p, voxel_size, gap)
    if workers is None:
        workers = (os.cpu_count() or 1) if k >= PARALLEL_FROM else 1
    if workers <= 1:
        arrays = [_piece_arrays(p, voxel_size, gap) for p in pieces]
    else:
        with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as pool:
            chunk = max(1, k // (4 * workers))
            arrays = list(pool.map(_piece_arrays, pieces, [voxel_size] * k, [gap] * k, chunksize=chunk))
    return [trimesh.Trimesh(v, f, process=False) for v, f in arrays]
