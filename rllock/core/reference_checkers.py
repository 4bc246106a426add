"""The three checkers and the chunk sampler, written plainly over sets of voxel coordinates.

This is the definition (docs/checkers.md) in code, kept short so that it can be read and trusted; the
verifier uses it, and the compiled fast path in `rllock.core.compiled_checkers` is tested against it.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Sequence
from itertools import combinations

import numpy as np

Voxel = tuple[int, int, int]
Part = frozenset[Voxel]


def voxel(xyz) -> Voxel:
    """A voxel of a grid coordinate row (numpy integers become ints)."""
    return int(xyz[0]), int(xyz[1]), int(xyz[2])


DIRECTIONS: tuple[Voxel, ...] = ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1))
DIRECTION_NAMES = ("+x", "-x", "+y", "-y", "+z", "-z")
REMOVAL_MODES = ("straight", "path")


def shift(v: Voxel, d: Voxel, t: int = 1) -> Voxel:
    return (v[0] + t * d[0], v[1] + t * d[1], v[2] + t * d[2])


def is_connected(cells: Iterable[Voxel]) -> bool:
    cells = set(cells)
    if not cells:
        return False
    start = next(iter(cells))
    seen, queue = {start}, deque([start])
    while queue:
        v = queue.popleft()
        for d in DIRECTIONS:
            u = shift(v, d)
            if u in cells and u not in seen:
                seen.add(u)
                queue.append(u)
    return len(seen) == len(cells)


def bbox(cells: Iterable[Voxel]) -> tuple[np.ndarray, np.ndarray]:
    arr = np.array(list(cells))
    return arr.min(axis=0), arr.max(axis=0)


def straight_exit(piece: Part, rest: Part) -> tuple[int, int] | None:
    """(direction index, steps) of the first axis direction along which `piece` slides out of `rest`'s
    bounding box without any voxel passing through `rest`; None if every direction is blocked."""
    lo, hi = bbox(piece | rest)
    reach = int((hi - lo).max()) + 1
    for k, d in enumerate(DIRECTIONS):
        if all(shift(v, d, t) not in rest for v in piece for t in range(1, reach + 1)):
            return k, _steps_to_clear(piece, rest, d)
    return None


def _steps_to_clear(piece: Part, rest: Part, d: Voxel) -> int:
    """Unit moves along d after which piece's bounding box no longer overlaps rest's."""
    plo, phi = bbox(piece)
    rlo, rhi = bbox(rest)
    axis = next(a for a in range(3) if d[a] != 0)
    if d[axis] > 0:
        return max(0, int(rhi[axis] - plo[axis]) + 1)
    return max(0, int(phi[axis] - rlo[axis]) + 1)


def path_exit(piece: Part, rest: Part) -> list[int] | None:
    """Shortest sequence of collision-free unit moves (direction indices) that takes `piece` out of
    `rest`'s bounding box (DESIA's removability test), or None when no such sequence exists."""
    plo, phi = bbox(piece)
    rlo, rhi = bbox(rest)

    def outside(off: Voxel) -> bool:
        return any(phi[a] + off[a] < rlo[a] or plo[a] + off[a] > rhi[a] for a in range(3))

    def free(off: Voxel) -> bool:
        return all(shift(v, off) not in rest for v in piece)

    start: Voxel = (0, 0, 0)
    parent: dict[Voxel, tuple[Voxel, int] | None] = {start: None}
    queue = deque([start])
    while queue:
        off = queue.popleft()
        if outside(off):
            moves: list[int] = []
            while parent[off] is not None:
                off, k = parent[off]  # type: ignore[misc]
                moves.append(k)
            return moves[::-1]
        for k, d in enumerate(DIRECTIONS):
            nxt = shift(off, d)
            if nxt not in parent and free(nxt):
                parent[nxt] = (off, k)
                queue.append(nxt)
    return None


def is_removable(piece: Part, rest: Part, removal: str) -> bool:
    if removal == "straight":
        return straight_exit(piece, rest) is not None
    return path_exit(piece, rest) is not None


def blocking_graph(parts: Sequence[Part], axis: int) -> set[tuple[int, int]]:
    """Edges p -> q where some voxel v of p has a voxel of q at v + e_axis (q blocks p moving +axis)."""
    owner = {v: k for k, part in enumerate(parts) for v in part}
    d = DIRECTIONS[2 * axis]
    edges = set()
    for v, p in owner.items():
        q = owner.get(shift(v, d))
        if q is not None and q != p:
            edges.add((p, q))
    return edges


def strongly_connected_components(n: int, edges: set[tuple[int, int]]) -> list[frozenset[int]]:
    """SCCs by mutual reachability (transitive closure): quadratic, and plainly right."""
    reach = [{p} for p in range(n)]
    changed = True
    while changed:
        changed = False
        for p, q in edges:
            if not reach[q] <= reach[p]:
                reach[p] |= reach[q]
                changed = True
    return list({frozenset(q for q in range(n) if p in reach[q] and q in reach[p]) for p in range(n)})


def is_interlocking(parts: Sequence[Part]) -> bool:
    """parts[0] is the key. On every axis the blocking graph has one SCC, or two with the key alone."""
    for axis in range(3):
        sccs = strongly_connected_components(len(parts), blocking_graph(parts, axis))
        if not (len(sccs) == 1 or (len(sccs) == 2 and frozenset({0}) in sccs)):
            return False
    return True


def is_interlocking_bruteforce(parts: Sequence[Part]) -> bool:
    """The definition itself: no proper subset of the parts can translate along any of the 6 directions,
    except the key alone (or, equivalently, everything but the key). Exponential: small cases only."""
    everything = set().union(*parts)
    n = len(parts)
    for size in range(1, n):
        for subset in combinations(range(n), size):
            if set(subset) in ({0}, set(range(1, n))):
                continue
            cells = set().union(*(parts[k] for k in subset))
            others = everything - cells
            for d in DIRECTIONS:
                if all(shift(v, d) not in others for v in cells):
                    return False
    return True


def sample_chunk(
    labels: dict[Voxel, int], piece: int, size: int, rng: np.random.Generator
) -> list[Voxel] | None:
    """One raw chunk for piece `piece` (1-based) from a state where label 0 is the remaining volume.

    The first voxel is drawn uniformly from the remaining voxels that face-touch piece `piece - 1`
    (for the first piece, from all remaining voxels); each next voxel uniformly from the distinct
    remaining voxels that face-touch the growing chunk. None when the chunk cannot grow to `size`.
    """
    remaining = {v for v, lab in labels.items() if lab == 0}
    if piece == 1:
        seeds = sorted(remaining)
    else:
        seeds = sorted(v for v in remaining if any(labels.get(shift(v, d)) == piece - 1 for d in DIRECTIONS))
    if not seeds:
        return None
    chunk = [seeds[rng.integers(len(seeds))]]
    while len(chunk) < size:
        frontier = sorted({shift(v, d) for v in chunk for d in DIRECTIONS} & remaining - set(chunk))
        if not frontier:
            return None
        chunk.append(frontier[rng.integers(len(frontier))])
    return chunk
