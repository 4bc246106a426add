"""Lookup tables over the voxels of one shape, in the compact voxel indexing the fast path uses.

Voxels are numbered 0..N-1 in `np.argwhere` order of the `[x, y, z]` grid. Direction k is
`reference.DIRECTIONS[k]` (+x, -x, +y, -y, +z, -z); the opposite of k is k ^ 1.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from rllock.core.reference_checkers import DIRECTIONS


@dataclass(frozen=True, eq=False)
class Topology:
    grid: np.ndarray  # bool[X, Y, Z]
    coords: np.ndarray  # int32[N, 3]
    index: np.ndarray  # int32[X, Y, Z]: voxel number, -1 where empty
    nbr: np.ndarray  # int32[N, 6]: face neighbour in direction k, -1 if none
    ray: np.ndarray  # int32[N, 6]: nearest voxel strictly beyond v along direction k, -1 if none
    line: np.ndarray  # int32[N, 3]: id of the axis-a line through v (unique per axis)
    n_lines: int

    @property
    def size(self) -> int:
        return int(self.coords.shape[0])

    @property
    def dims(self) -> tuple[int, int, int]:
        return tuple(int(d) for d in self.grid.shape)  # type: ignore[return-value]

    @property
    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, np.ndarray, np.ndarray]:
        """(nbr, ray, line, n_lines, coords, index): the compiled checkers' and sampler's
        tables, as one argument."""
        return (self.nbr, self.ray, self.line, self.n_lines, self.coords, self.index)

    def to_grid(self, labels: np.ndarray) -> np.ndarray:
        """Per-voxel values scattered into an int grid `[x, y, z]` (0 where the shape is empty)."""
        out = np.zeros(self.grid.shape, dtype=np.int64)
        out[tuple(self.coords.T)] = labels
        return out


def build_topology(grid: np.ndarray) -> Topology:
    grid = np.asarray(grid, dtype=bool)
    dims = np.array(grid.shape)
    # C order: np.argwhere gives Fortran order, and the threads' copies (`SamplingPool.own`) C order,
    # each a numba signature of its own to compile.
    coords = np.ascontiguousarray(np.argwhere(grid), dtype=np.int32)
    index = np.full(grid.shape, -1, dtype=np.int32)
    index[tuple(coords.T)] = np.arange(len(coords), dtype=np.int32)
    nbr = np.full((len(coords), 6), -1, dtype=np.int32)
    ray = np.full((len(coords), 6), -1, dtype=np.int32)
    for k, d in enumerate(DIRECTIONS):
        step = np.array(d)
        for t in range(int(dims.max()), 0, -1):
            # Walk from far to near so the nearest voxel along the ray is written last.
            target = coords + t * step
            inside = np.all((target >= 0) & (target < dims), axis=1)
            hit = np.full(len(coords), -1, dtype=np.int32)
            hit[inside] = index[tuple(target[inside].T)]
            ray[hit >= 0, k] = hit[hit >= 0]
            if t == 1:
                nbr[:, k] = hit
    x, y, z = coords.T
    line = np.stack([y * dims[2] + z, x * dims[2] + z, x * dims[1] + y], axis=1).astype(np.int32)
    n_lines = int(max(dims[1] * dims[2], dims[0] * dims[2], dims[0] * dims[1]))
    return Topology(grid, coords, index, nbr, ray, line, n_lines)


def symmetries(topology: Topology) -> np.ndarray:
    """int32[S, N]: voxel permutations of the shape's symmetries among the 48 axis permutations and
    reflections of the grid (identity first); row s maps voxel v to voxel `out[s, v]`.

    The checkers see only axis-aligned contacts and translations, and an axis permutation or reflection
    maps those onto each other, so a symmetry maps valid states to valid states and accepted chunks to
    accepted chunks: training data can be augmented with them (AlphaGo Zero's dihedral trick in 3D)."""
    grid, coords = topology.grid, topology.coords
    dims = np.array(grid.shape)
    out = []
    for axes in itertools.permutations(range(3)):
        for flips in itertools.product((False, True), repeat=3):
            new_dims = dims[list(axes)]
            if tuple(new_dims) != grid.shape:
                continue
            moved = coords[:, axes].copy()
            for a, flip in enumerate(flips):
                if flip:
                    moved[:, a] = new_dims[a] - 1 - moved[:, a]
            target = topology.index[tuple(moved.T)]
            if np.all(target >= 0):  # the shape lands on itself (a bijection, since N voxels land on N)
                out.append(target)
    return np.stack(out).astype(np.int32)
