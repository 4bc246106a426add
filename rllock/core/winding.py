"""Generalized winding numbers of triangle meshes that need not be closed (Jacobson et al. 2013), fast
(Barill et al. 2018): what decides inside and outside for meshes with holes, open seams or
self-intersections.

The winding number of a point q is the signed solid angle the surface covers seen from q, over 4 pi: 1
inside a closed surface, 0 outside, and for a surface with small holes or overlaps still close to 1
inside and to 0 outside, so a point is inside when it is above 1/2. A triangle's solid angle is exact
(Van Oosterom and Strackee's formula). A tree of triangle clusters makes it fast: seen from far enough
away (more than BETA times the cluster's radius), a cluster's solid angle is that of a dipole at its
area-weighted centre with the sum of its area-weighted normals, A n . (p - q) / |p - q|^3, so a point
costs about the logarithm of the triangle count instead of all triangles.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange

from rllock.core import numba_cache  # noqa: F401  (before any @njit: it picks the cache folder)

# A cluster is replaced by its dipole when the point is farther than BETA times its radius. Barill et
# al. use 2 with a second-order expansion; the first-order dipole here needs more distance for the same
# accuracy (the tests hold winding numbers within 0.01 of the exact ones).
BETA = 3.0
LEAF = 16


class Tree(NamedTuple):
    """Clusters of a mesh's triangles: node i holds triangles order[start[i]:end[i]] and, unless it is a
    leaf (left[i] == -1), children left[i] and right[i]."""

    corners: np.ndarray  # float64[F, 3, 3]: triangle corners, in tree order
    left: np.ndarray  # int64[M]
    right: np.ndarray  # int64[M]
    start: np.ndarray  # int64[M]
    end: np.ndarray  # int64[M]
    centre: np.ndarray  # float64[M, 3]: area-weighted centroid
    dipole: np.ndarray  # float64[M, 3]: sum of area * unit normal (half the cross products)
    radius: np.ndarray  # float64[M]: the farthest corner from the centre


def build_tree(vertices: np.ndarray, faces: np.ndarray) -> Tree:
    """The cluster tree of a triangle mesh: clusters split at the median of their centroids along their
    longest side, down to LEAF triangles."""
    corners = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    centroids = corners.mean(axis=1)
    order = np.arange(len(corners))
    nodes: list[list[int]] = []  # [left, right, start, end]
    todo = [(0, len(corners), -1, 0)]  # (start, end, parent, which child)
    while todo:
        lo, hi, parent, side = todo.pop()
        me = len(nodes)
        nodes.append([-1, -1, lo, hi])
        if parent >= 0:
            nodes[parent][side] = me
        if hi - lo <= LEAF:
            continue
        part = order[lo:hi]
        axis = int(np.argmax(np.ptp(centroids[part], axis=0)))
        mid = (hi - lo) // 2
        order[lo:hi] = part[np.argpartition(centroids[part, axis], mid)]
        todo += [(lo, lo + mid, me, 0), (lo + mid, hi, me, 1)]
    corners = corners[order]
    table = np.array(nodes, dtype=np.int64)
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]) / 2
    area = np.linalg.norm(cross, axis=1)
    weighted = np.concatenate([[np.zeros(3)], np.cumsum(area[:, None] * corners.mean(axis=1), axis=0)])
    areas = np.concatenate([[0.0], np.cumsum(area)])
    dipoles = np.concatenate([[np.zeros(3)], np.cumsum(cross, axis=0)])
    start, end = table[:, 2], table[:, 3]
    total = areas[end] - areas[start]
    mean = corners[:, 0].copy()  # a corner, for clusters of zero area
    centre = np.where(
        total[:, None] > 0,
        (weighted[end] - weighted[start]) / np.maximum(total, 1e-300)[:, None],
        mean[np.minimum(start, len(mean) - 1)],
    )
    radius = np.array(
        [
            np.linalg.norm(corners[s:e].reshape(-1, 3) - centre[i], axis=1).max()
            for i, (s, e) in enumerate(zip(start, end))
        ]
    )
    return Tree(corners, table[:, 0], table[:, 1], start, end, centre, dipoles[end] - dipoles[start], radius)


@njit(cache=True, nogil=True)
def _triangle_angle(t, q):
    """The signed solid angle of triangle t (its 3 x 3 corners) seen from q (Van Oosterom, Strackee)."""
    ax, ay, az = t[0, 0] - q[0], t[0, 1] - q[1], t[0, 2] - q[2]
    bx, by, bz = t[1, 0] - q[0], t[1, 1] - q[1], t[1, 2] - q[2]
    cx, cy, cz = t[2, 0] - q[0], t[2, 1] - q[1], t[2, 2] - q[2]
    la = np.sqrt(ax * ax + ay * ay + az * az)
    lb = np.sqrt(bx * bx + by * by + bz * bz)
    lc = np.sqrt(cx * cx + cy * cy + cz * cz)
    det = ax * (by * cz - bz * cy) - ay * (bx * cz - bz * cx) + az * (bx * cy - by * cx)
    dot = la * lb * lc + (ax * bx + ay * by + az * bz) * lc + (ax * cx + ay * cy + az * cz) * lb
    dot += (bx * cx + by * cy + bz * cz) * la
    return 2.0 * np.arctan2(det, dot)


@njit(cache=True, nogil=True)
def _winding(q, corners, left, right, start, end, centre, dipole, radius, stack):
    total = 0.0
    top = 1
    stack[0] = 0
    while top > 0:
        top -= 1
        i = stack[top]
        dx, dy, dz = centre[i, 0] - q[0], centre[i, 1] - q[1], centre[i, 2] - q[2]
        dist2 = dx * dx + dy * dy + dz * dz
        if dist2 > (BETA * radius[i]) ** 2:
            total += (dipole[i, 0] * dx + dipole[i, 1] * dy + dipole[i, 2] * dz) / dist2**1.5
        elif left[i] < 0:
            for t in range(start[i], end[i]):
                total += _triangle_angle(corners[t], q)
        else:
            stack[top] = left[i]
            stack[top + 1] = right[i]
            top += 2
    return total / (4.0 * np.pi)


@njit(cache=True, parallel=True)
def _winding_many(points, corners, left, right, start, end, centre, dipole, radius):
    out = np.empty(points.shape[0])
    for p in prange(points.shape[0]):
        stack = np.empty(128, np.int64)
        out[p] = _winding(points[p], corners, left, right, start, end, centre, dipole, radius, stack)
    return out


def winding_numbers(tree: Tree, points: np.ndarray) -> np.ndarray:
    """The generalized winding number of each point (float64[P, 3]) with respect to the tree's mesh."""
    return _winding_many(np.ascontiguousarray(points, dtype=np.float64), *tree)


def winding_numbers_exact(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The same, summed over every triangle: the reference the tree is tested against."""
    corners = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    a, b, c = (corners[None, :, i, :] - points[:, None, :] for i in range(3))
    la, lb, lc = (np.linalg.norm(x, axis=2) for x in (a, b, c))
    det = np.einsum("pti,pti->pt", a, np.cross(b, c))
    dot = la * lb * lc + (a * b).sum(2) * lc + (a * c).sum(2) * lb + (b * c).sum(2) * la
    return (2 * np.arctan2(det, dot)).sum(axis=1) / (4 * np.pi)
