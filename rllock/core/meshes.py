"""Mesh models to voxel shapes (reading their files is `rllock.core.mesh_files`): cleaning a mesh, deciding
its inside, voxelizing it (the other way, pieces to meshes for export, is `rllock.core.piece_meshes`).

A mesh is sampled on a grid whose longest side has `resolution` voxels, mesh axes kept, at
SUBSAMPLES^3 evenly spread points per voxel (its centre among them), each layer of points tested against the
solid's cross-section at that height (or, for a mesh that stays open once merged and capped, by its
generalized winding number above 1/2: `rllock.core.winding`). A voxel is filled when its centre is inside the
solid, or more than half its sub-samples are. The half rule never thickens a model: where the solid's part of
a voxel is convex and misses the centre, every sub-sample inside mirrors through the centre to one outside, so
it only adds voxels cut by a slot or groove through their centre. (A lower share would grow every surface by
up to half a voxel; the share alone, without the centre, would lose thin rods that run through the centres.)
Features thinner than a voxel still slip between the centres: a slanted ear or leg becomes a chain of parts
that touch only along edges or corners, or not at all. So the parts are then joined through empty voxels
wherever the solid runs from one to the next (two facing sub-samples, one each side of a voxel face, both
inside), by the fewest voxels and then those that hold the most solid. Voxels are only added where the solid
is, never across empty space, so separate objects stay apart unless they come within about a voxel of each
other, where voxels cannot tell them apart anyway. Only the largest 6-connected part is kept, with a warning
that says how many voxels were dropped; when that drops more than MAX_DROPPED of them the mesh is refused.
Both name a higher resolution that keeps the parts together where one up to twice the given one does.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import manifold3d as m3
import numpy as np
import trimesh
from scipy import ndimage
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from rllock.core.mesh_files import read_triangles
from rllock.core.winding import build_tree, winding_numbers
from rllock.errors import RLLockError

DEFAULT_RESOLUTION = 8
# The share of a mesh's voxels that may be dropped (parts that no solid joins to the rest, as the voxels'
# sub-samples see it) before the shape is too far from the model to search.
MAX_DROPPED = 0.25

log = logging.getLogger(__name__)


def _load_mesh(path: Path) -> trimesh.Trimesh:
    """The mesh's triangles with vertices merged by position, its holes capped when they are simple loops
    (`_capped`); a mesh whose open edges are not is returned open, for the winding numbers to fill."""
    vertices, faces = read_triangles(path)
    # Only the geometry: textured and smooth-shaded models repeat a vertex wherever its texture
    # coordinates or normal change, which leaves the surface open along every seam until the copies are
    # merged by position (a mesh without texture or normals merges them so on load).
    mesh = trimesh.Trimesh(vertices, faces, process=True)
    extent = np.asarray(mesh.extents, dtype=float)
    if extent.min() <= 1e-9 * extent.max():
        raise RLLockError(f"mesh {path} is flat (no thickness along one axis): it has no inside to fill")
    if mesh.is_watertight:
        return mesh
    capped, holes = _capped(mesh)
    if capped is None or not capped.is_watertight:
        return mesh
    log.warning("mesh %s had %d hole(s) in its surface: closed each with a flat cap", path, holes)
    return capped


def _capped(mesh: trimesh.Trimesh) -> tuple[trimesh.Trimesh | None, int]:
    """(`mesh` with each hole closed by a fan of triangles to the hole's centroid, the number of holes),
    or (None, 0) when its open edges (edges of one face) do not form simple loops. Scanned models, such
    as the Stanford bunny, come with holes where the scanner saw nothing."""
    mesh = mesh.copy()
    mesh.merge_vertices()
    edges, counts = np.unique(mesh.edges_sorted, axis=0, return_counts=True)
    open_edges = {(int(a), int(b)) for a, b in edges[counts == 1]}
    # Each open edge, directed against its face's winding, so that the caps wind as the surface does.
    after: dict[int, int] = {}
    for a, b in mesh.edges:  # face edges, in winding order
        if (min(a, b), max(a, b)) in open_edges:
            if int(b) in after:  # two holes meet at a vertex: not a simple loop
                return None, 0
            after[int(b)] = int(a)
    vertices, faces = [np.asarray(mesh.vertices)], [np.asarray(mesh.faces)]
    done: set[int] = set()
    holes = 0
    for start in after:
        if start in done:
            continue
        loop, v = [], start
        while v not in done:
            done.add(v)
            loop.append(v)
            v = after.get(v, -1)
            if v == -1:  # an open path, not a loop
                return None, 0
        if v != start:
            return None, 0
        centre = len(mesh.vertices) + holes
        vertices.append(np.asarray(mesh.vertices)[loop].mean(axis=0, keepdims=True))
        faces.append(np.array([[loop[i], loop[(i + 1) % len(loop)], centre] for i in range(len(loop))]))
        holes += 1
    return trimesh.Trimesh(np.concatenate(vertices), np.concatenate(faces)), holes


def _solid(mesh: trimesh.Trimesh) -> m3.Manifold | None:
    """The mesh as a manifold3d solid, or None when it is not a closed 2-manifold (open, or with edges of
    more than two faces)."""
    if not mesh.is_watertight:
        return None
    solid = m3.Manifold(
        m3.Mesh(
            vert_properties=np.asarray(mesh.vertices, dtype=np.float32),
            tri_verts=np.asarray(mesh.faces, dtype=np.uint32),
        )
    )
    return solid if solid.status() == m3.Error.NoError else None


class _Inside(NamedTuple):
    """What decides inside and outside: the bounds of the model and, for the points (xs[i], ys[j], z) of
    one layer, whether each is inside (bool[len(xs), len(ys)])."""

    lo: np.ndarray
    hi: np.ndarray
    layer: Callable[[float, np.ndarray, np.ndarray], np.ndarray]
    closed: bool  # decided by the closed solid's cross-sections, not by winding numbers


def _inside(mesh: trimesh.Trimesh, path: Path) -> _Inside:
    """A closed mesh decides by its solid's cross-sections (exact and fast); any other by generalized
    winding numbers above 1/2 (`rllock.core.winding`), which tolerate open seams, holes and
    self-intersections."""
    solid = _solid(mesh)
    if solid is not None:
        box = np.asarray(solid.bounding_box(), dtype=float)

        def sliced(z: float, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
            return _inside_rows(solid.slice(z).to_polygons(), xs, ys)

        return _Inside(box[:3], box[3:], sliced, True)
    tree = build_tree(mesh.vertices, mesh.faces)
    open_edges = int((np.unique(mesh.edges_sorted, axis=0, return_counts=True)[1] == 1).sum())
    log.warning(
        "mesh %s is not closed (%d open edges): inside and outside decided by winding numbers",
        path,
        open_edges,
    )

    def wound(z: float, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        gx, gy = np.meshgrid(xs, ys, indexing="ij")
        points = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], axis=1)
        return (winding_numbers(tree, points) > 0.5).reshape(gx.shape)

    lo, hi = np.asarray(mesh.bounds, dtype=float)
    return _Inside(lo, hi, wound, False)


def _frame(lo: np.ndarray, hi: np.ndarray, resolution: int) -> tuple[np.ndarray, float, np.ndarray]:
    """(origin, pitch, dims): the voxel grid centred on the box lo..hi, `resolution` voxels along its
    longest side."""
    extent = hi - lo
    pitch = float(extent.max()) / resolution
    if pitch <= 0:
        raise RLLockError("the mesh has no volume")
    # The tolerance keeps an exact multiple of the pitch from gaining a voxel to rounding.
    dims = np.maximum(1, np.ceil(extent / pitch - 1e-6)).astype(int)
    return (lo + hi) / 2 - dims * pitch / 2, pitch, dims


def _inside_rows(contours: list[np.ndarray], xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Boolean [i, j]: whether (xs[i], ys[j]) lies inside the contours (even-odd), for sorted xs and ys.

    Each row counts the contour edges it crosses left of each point: one pass over the edges and one
    cumulative sum, where testing every point against every edge grows with their product.
    """
    if not contours:
        return np.zeros((len(xs), len(ys)), dtype=bool)
    starts = np.concatenate(contours)
    ends = np.concatenate([np.roll(c, -1, axis=0) for c in contours])
    # Rows at or above an edge's lower end and below its upper one: a row through a vertex counts one
    # crossing where the contour passes through and zero or two where it turns back.
    first = np.searchsorted(ys, np.minimum(starts[:, 1], ends[:, 1]))
    stop = np.searchsorted(ys, np.maximum(starts[:, 1], ends[:, 1]))
    spans = stop - first
    edge = np.repeat(np.arange(len(starts)), spans)
    row = first[edge] + np.arange(int(spans.sum())) - np.repeat(np.cumsum(spans) - spans, spans)
    t = (ys[row] - starts[edge, 1]) / (ends[edge, 1] - starts[edge, 1])
    x = starts[edge, 0] + t * (ends[edge, 0] - starts[edge, 0])
    column = np.searchsorted(xs, x, side="right")  # the first point right of the crossing
    width = len(xs) + 1
    crossings = np.bincount(row * width + column, minlength=len(ys) * width).reshape(len(ys), width)
    return (np.cumsum(crossings, axis=1)[:, :-1] % 2 == 1).T


# Sub-samples per voxel along each axis: odd, so that the voxel's centre is one of them.
SUBSAMPLES = 5


class _Samples(NamedTuple):
    """What the sub-samples of a voxel grid [x, y, z] see of a solid."""

    centre: np.ndarray  # whether each voxel's centre is inside
    overlap: np.ndarray  # how many of each voxel's SUBSAMPLES^3 sub-samples are inside
    # Per axis a, [.., i, ..] along a: how many pairs of sub-samples facing each other across the face
    # between voxels i and i + 1 are both inside, so that the solid most likely crosses that face there.
    across: tuple[np.ndarray, np.ndarray, np.ndarray]


def _sample(inside: _Inside, resolution: int) -> _Samples:
    """The model sampled at SUBSAMPLES^3 evenly spread points per voxel, a layer at a time (`_Inside`):
    a closed solid's cross-section at the layer's height is fast and robust, where casting a ray per
    point is slow on meshes of many triangles."""
    origin, pitch, dims = _frame(inside.lo, inside.hi, resolution)
    k = SUBSAMPLES
    # A tiny irrational nudge keeps sample points off faces that lie exactly on a plane of samples (such
    # as the plane of centres halfway between grid planes), where inside and outside would be a tie.
    nudge = 1e-4 * np.sqrt((2, 3, 5))
    axes = [origin[a] + ((np.arange(k * dims[a]) + 0.5) / k + nudge[a]) * pitch for a in range(3)]
    nx, ny, nz = (int(d) for d in dims)
    centre = np.zeros((nx, ny, nz), dtype=bool)
    overlap = np.zeros((nx, ny, nz), dtype=np.int64)
    across = (
        np.zeros((nx - 1, ny, nz), dtype=np.int64),
        np.zeros((nx, ny - 1, nz), dtype=np.int64),
        np.zeros((nx, ny, nz - 1), dtype=np.int64),
    )
    below = np.zeros((k * nx, k * ny), dtype=bool)
    for iz, z in enumerate(axes[2]):
        layer = inside.layer(float(z), axes[0], axes[1])
        cell = iz // k
        overlap[:, :, cell] += layer.reshape(nx, k, ny, k).sum(axis=(1, 3))
        if iz % k == k // 2:
            centre[:, :, cell] = layer[k // 2 :: k, k // 2 :: k]
        # The last sub-samples of each voxel and the first of the next one, along x and along y.
        facing_x = layer[k - 1 : -1 : k] & layer[k::k]
        facing_y = layer[:, k - 1 : -1 : k] & layer[:, k::k]
        across[0][:, :, cell] += facing_x.reshape(nx - 1, ny, k).sum(axis=2)
        across[1][:, :, cell] += facing_y.reshape(nx, k, ny - 1).sum(axis=1)
        if iz % k == 0 and iz > 0:
            across[2][:, :, cell - 1] = (below & layer).reshape(nx, k, ny, k).sum(axis=(1, 3))
        below = layer
    return _Samples(centre, overlap, across)


def _face_pairs(shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Every pair of face-neighbouring cells of a grid once, as flat indices (u, w), axis by axis in the
    order of `_Samples.across`."""
    index = np.arange(int(np.prod(shape))).reshape(shape)
    along = [np.moveaxis(index, axis, 0) for axis in range(3)]
    return np.concatenate([a[:-1].ravel() for a in along]), np.concatenate([a[1:].ravel() for a in along])


def _root(parent: list[int], label: int) -> int:
    """The label that stands for `label`'s set (union-find, halving paths on the way)."""
    while parent[label] != label:
        parent[label] = parent[parent[label]]
        label = parent[label]
    return label


def _bridge(filled: np.ndarray, samples: _Samples) -> np.ndarray:
    """`filled` with its 6-connected parts joined through empty cells wherever the solid connects them,
    as its sub-samples see it: each join by the fewest cells, then by those that overlap it most.

    Steps go between face neighbours across whose face the solid passes. Mehlhorn's approximation of
    the cheapest tree that joins all parts: shortest paths from all parts at once give every reachable
    cell to its nearest part, and a minimum spanning tree over the parts whose cells meet picks the
    joins, each the two shortest paths to where they meet.
    """
    parts, count = ndimage.label(filled)  # the default structure is 6-connectivity
    if count <= 1:
        return filled
    n = filled.size
    # A cell costs 1, plus less than 1 in all for less overlap: the fewest cells, then the most overlap.
    cost = 1 + (1 - samples.overlap.ravel() / SUBSAMPLES**3) / (n + 1)
    u, w = _face_pairs(filled.shape)
    crossed = np.concatenate([np.moveaxis(c, a, 0).ravel() for a, c in enumerate(samples.across)]) > 0
    tails = np.concatenate([u[crossed], w[crossed]])
    heads = np.concatenate([w[crossed], u[crossed]])
    into_empty = ~filled.ravel()[heads]  # paths start in every part at once and never enter one
    tails, heads = tails[into_empty], heads[into_empty]
    graph = csr_matrix((cost[heads], (tails, heads)), shape=(n, n))
    sources = np.flatnonzero(filled)
    dist, previous, source = dijkstra(graph, indices=sources, return_predecessors=True, min_only=True)
    region = np.where(source >= 0, parts.ravel()[np.maximum(source, 0)], 0)
    meet = crossed & (region[u] > 0) & (region[w] > 0) & (region[u] != region[w])
    u, w = u[meet], w[meet]
    parent = list(range(count + 1))
    grid = filled.ravel().copy()
    for pair in np.lexsort((w, u, dist[u] + dist[w])):
        a, b = _root(parent, int(region[u[pair]])), _root(parent, int(region[w[pair]]))
        if a == b:
            continue
        parent[b] = a
        for cell in (int(u[pair]), int(w[pair])):
            while not grid[cell]:
                grid[cell] = True
                cell = int(previous[cell])
    return grid.reshape(filled.shape)


def _voxels(inside: _Inside, resolution: int) -> np.ndarray:
    """The voxels of the model (the module docstring gives the rule), before any part is dropped."""
    samples = _sample(inside, resolution)
    # The module docstring says why more than half the sub-samples never thickens a model.
    return _bridge(samples.centre | (2 * samples.overlap > SUBSAMPLES**3), samples)


def largest_component(grid: np.ndarray) -> np.ndarray:
    """The largest 6-connected part of a boolean grid."""
    parts, count = ndimage.label(grid)
    if count <= 1:
        return grid
    return parts == int(np.argmax(np.bincount(parts.ravel())[1:])) + 1


def voxelize_mesh(path: str | Path, resolution: int | None = None) -> np.ndarray:
    """A mesh file (`MESH_SUFFIXES`) as a boolean grid [x, y, z] (mesh axes kept), at most `resolution` voxels
    along its longest side, reduced to its largest 6-connected part with a warning; refused when that
    drops more than MAX_DROPPED of the voxels, or when the mesh has no inside. A mesh that is not closed
    is filled where its winding numbers are above 1/2 (`_inside`)."""
    resolution = DEFAULT_RESOLUTION if resolution is None else resolution
    if resolution < 1:
        raise RLLockError(f"the resolution must be at least 1 voxel, got {resolution}")
    path = Path(path)
    inside = _inside(_load_mesh(path), path)
    grid = _voxels(inside, resolution)
    if not grid.any():
        if not inside.closed:
            raise RLLockError(
                f"mesh {path} has no inside: its open surface encloses no voxel's centre at resolution "
                f"{resolution} (winding numbers below 1/2)"
            )
        raise RLLockError(f"mesh {path} fills no voxel at resolution {resolution}: try a higher resolution")
    kept = largest_component(grid)
    total = int(grid.sum())
    dropped = total - int(kept.sum())
    if dropped > MAX_DROPPED * total:
        raise RLLockError(
            f"mesh {path} at resolution {resolution} falls apart: its largest connected part keeps "
            f"{total - dropped} of {total} voxels; {_resolution_hint(inside, resolution)}"
        )
    if dropped:
        log.warning(
            "%s at resolution %d: kept the largest connected part, dropped %d of %d voxels; %s",
            path,
            resolution,
            dropped,
            total,
            _resolution_hint(inside, resolution),
        )
    return kept


def _resolution_hint(inside: _Inside, resolution: int) -> str:
    """The lowest resolution above `resolution` (up to twice it) at which the voxels form one connected
    part, as advice. Winding numbers cost too much to try them all: then only the advice to go higher."""
    if not inside.closed:
        return "a higher --resolution may keep its parts together"
    for higher in range(resolution + 1, 2 * resolution + 1):
        if ndimage.label(_voxels(inside, higher))[1] == 1:
            return f"--resolution {higher} keeps its parts together"
    return f"no resolution up to {2 * resolution} keeps them together (the model may have separate parts)"
