"""The full verifier: every stage A_1..A_(K-1) of an assembly through the checks of docs/checkers.md.

It is the reference checkers' definition (`reference_checkers`) computed once for the whole assembly
where it can be, so that 1,500 pieces take seconds, not hours: pieces' connectivity once each, the rests'
by a union-find that adds pieces from the last; straight removability from the largest label beyond each
voxel; interlocking by scipy's strongly connected components over the pieces' contacts. The tests hold
its verdicts, moves included, to the reference checkers applied stage by stage (`tests/helpers.py`).

Labels are an int grid `[x, y, z]`: 0 empty, 1..K the piece ids in disassembly order (1 = key).
"""

from __future__ import annotations

from collections import deque
from dataclasses import asdict, dataclass, field

import numpy as np
from scipy import ndimage
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from rllock.core import reference_checkers as ref
from rllock.errors import RLLockError

CHECKER_VERSION = "1"
CHECKER_NAME = "rllock.core.verifier (every stage by the checks of docs/checkers.md)"


@dataclass(frozen=True)
class Move:
    direction: str  # "+x", "-x", "+y", "-y", "+z" or "-z"
    steps: int


@dataclass(frozen=True)
class Verdict:
    valid: bool
    pieces: int
    removal: str
    failed_stage: int | None
    failed_check: str | None
    piece_sizes: list[int]
    disassembly: list[dict] = field(default_factory=list)  # [{"piece": i, "moves": [Move...]}], valid only

    def to_json(self) -> dict:
        return asdict(self)


def validate_labels(labels: np.ndarray, pieces: int | None = None) -> int:
    """K, after checking that the ids are exactly 1..K with K >= 2. `pieces` is K where the assembly's
    file names it; else K is the largest id."""
    labels = np.asarray(labels)
    ids = [int(i) for i in np.unique(labels[labels != 0])]
    if not ids:
        raise RLLockError("the assembly has no filled voxels")
    if pieces is not None:
        if pieces < 2:
            raise RLLockError(f"an assembly needs at least 2 pieces, not K = {pieces}")
        k = pieces
    else:
        positive = [i for i in ids if i >= 1]
        run = 0  # 1..run are all present
        while run < len(positive) and positive[run] == run + 1:
            run += 1
        above = positive[run:]
        # A value far above the others (99 among 1..11) is a stray label, not 87 missing pieces.
        k = run if above and len(above) < above[-1] - run - len(above) else max(positive, default=0)
    stray = [i for i in ids if i < 1 or i > k]
    if stray:
        where = tuple(int(c) for c in np.argwhere(labels == stray[0])[0])
        numbers = f"1..{k}" if k >= 2 else "1..K"
        raise RLLockError(f"label {stray[0]} at voxel {where} is not a piece number {numbers}")
    missing = sorted(set(range(1, k + 1)) - set(ids))
    if missing:
        raise RLLockError(f"piece ids must be 1..K without gaps (K = {k}); missing {missing[:5]}")
    if k < 2:
        raise RLLockError(f"an assembly needs at least 2 pieces, not K = {k}")
    return k


def _runs(directions: list[int]) -> list[Move]:
    moves: list[Move] = []
    for k in directions:
        name = ref.DIRECTION_NAMES[k]
        if moves and moves[-1].direction == name:
            moves[-1] = Move(name, moves[-1].steps + 1)
        else:
            moves.append(Move(name, 1))
    return moves


def label_cells(labels: np.ndarray, k: int) -> list[np.ndarray]:
    """The voxels of each label 0..K of a grid, int[n_j, 3] each (label 0: the empty ones), in one sort
    instead of K scans of the grid."""
    flat = labels.ravel()
    order = np.argsort(flat, kind="stable")
    bounds = np.searchsorted(flat[order], np.arange(k + 2))
    coords = np.stack(np.unravel_index(order, labels.shape), axis=1)
    return [coords[bounds[j] : bounds[j + 1]] for j in range(k + 1)]


def contact_pairs(labels: np.ndarray) -> list[np.ndarray]:
    """Per axis, the distinct label pairs (p, q), int[E, 2], where a voxel of piece p has one of piece q
    next to it along +axis."""
    out = []
    for axis in range(3):
        a = np.moveaxis(labels, axis, 0)
        p, q = a[:-1].ravel(), a[1:].ravel()
        touching = (p > 0) & (q > 0) & (p != q)
        out.append(np.unique(np.stack([p[touching], q[touching]], axis=1), axis=0))
    return out


@dataclass(frozen=True)
class _Assembly:
    """What the stage checks read, computed once for all stages: the labels, each piece's voxels and
    bounding box, the bounding box of each stage's rest R_i (pieces above i), and per direction k the
    largest label strictly beyond each voxel (`beyond[k]`), so that piece i slides out along k exactly
    when no voxel of it has a label above i beyond it."""

    labels: np.ndarray  # int grid [x, y, z], 0 empty
    cells: list[np.ndarray]  # cells[j]: int[n_j, 3], the voxels of piece j (cells[0] unused)
    lo: np.ndarray  # int[K + 1, 3]: piece j's bounding box lo[j]..hi[j]
    hi: np.ndarray
    rest_lo: np.ndarray  # int[K + 1, 3]: R_i's bounding box rest_lo[i]..rest_hi[i] (i < K)
    rest_hi: np.ndarray
    beyond: list[np.ndarray]  # per direction k, int grid

    @classmethod
    def of(cls, labels: np.ndarray, k: int) -> _Assembly:
        cells = label_cells(labels, k)
        lo = np.array([c.min(axis=0) if len(c) else (0, 0, 0) for c in cells])
        hi = np.array([c.max(axis=0) if len(c) else (0, 0, 0) for c in cells])
        rest_lo, rest_hi = lo.copy(), hi.copy()
        for i in range(k - 1, 0, -1):
            rest_lo[i] = np.minimum(lo[i + 1], rest_lo[i + 1]) if i + 1 < k else lo[k]
            rest_hi[i] = np.maximum(hi[i + 1], rest_hi[i + 1]) if i + 1 < k else hi[k]
        beyond = []
        for d in ref.DIRECTIONS:
            axis = next(a for a in range(3) if d[a])
            ahead = labels if d[axis] > 0 else np.flip(labels, axis)
            # The largest label at or beyond each voxel, then shifted one voxel back: strictly beyond.
            at_or_beyond = np.flip(np.maximum.accumulate(np.flip(ahead, axis), axis=axis), axis)
            strictly = np.zeros_like(at_or_beyond)
            src = [slice(None)] * 3
            dst = [slice(None)] * 3
            src[axis], dst[axis] = slice(1, None), slice(None, -1)
            strictly[tuple(dst)] = at_or_beyond[tuple(src)]
            beyond.append(strictly if d[axis] > 0 else np.flip(strictly, axis))
        return cls(labels, cells, lo, hi, rest_lo, rest_hi, beyond)

    def piece_connected(self, j: int) -> bool:
        cells = self.cells[j] - self.lo[j]
        box = np.zeros(self.hi[j] - self.lo[j] + 1, dtype=bool)
        box[tuple(cells.T)] = True
        return ndimage.label(box)[1] == 1  # the default structure is 6-connectivity

    def rests_connected(self) -> list[bool]:
        """connected[i]: whether R_i is 6-connected, for i = 0..K-1: the pieces added from K down, one at a
        time, to a union-find over voxels that counts the components."""
        k = len(self.cells) - 1
        index = np.full(self.labels.shape, -1, dtype=np.int64)
        parent: list[int] = []
        components = 0
        connected = [False] * k
        dims = self.labels.shape

        def root(v: int) -> int:
            while parent[v] != v:
                parent[v] = parent[parent[v]]
                v = parent[v]
            return v

        for j in range(k, 0, -1):
            for x, y, z in self.cells[j].tolist():
                me = len(parent)
                parent.append(me)
                index[x, y, z] = me
                components += 1
                for dx, dy, dz in ref.DIRECTIONS:
                    ux, uy, uz = x + dx, y + dy, z + dz
                    if 0 <= ux < dims[0] and 0 <= uy < dims[1] and 0 <= uz < dims[2]:
                        u = int(index[ux, uy, uz])
                        if u >= 0:
                            a, b = root(me), root(u)
                            if a != b:
                                parent[b] = a
                                components -= 1
            connected[j - 1] = components == 1
        return connected

    def straight_moves(self, i: int) -> list[Move] | None:
        """Piece i's move along the first free direction (`ref.straight_exit`'s order and steps)."""
        x, y, z = self.cells[i].T
        for k, d in enumerate(ref.DIRECTIONS):
            if self.beyond[k][x, y, z].max() <= i:
                axis = next(a for a in range(3) if d[a])
                if d[axis] > 0:
                    steps = max(0, int(self.rest_hi[i][axis] - self.lo[i][axis]) + 1)
                else:
                    steps = max(0, int(self.hi[i][axis] - self.rest_lo[i][axis]) + 1)
                return [Move(ref.DIRECTION_NAMES[k], steps)]
        return None

    def path_moves(self, i: int) -> list[Move] | None:
        """Piece i's shortest run of unit moves out of R_i's bounding box (`ref.path_exit`'s search: the
        same order, so the same moves)."""
        cells, dims = self.cells[i], np.array(self.labels.shape)
        plo, phi, rlo, rhi = self.lo[i], self.hi[i], self.rest_lo[i], self.rest_hi[i]

        def free(off: tuple[int, int, int]) -> bool:
            moved = cells + off
            inside = np.all((moved >= 0) & (moved < dims), axis=1)
            return not (self.labels[tuple(moved[inside].T)] > i).any()

        start = (0, 0, 0)
        parent: dict[tuple[int, int, int], tuple[tuple[int, int, int], int] | None] = {start: None}
        queue = deque([start])
        while queue:
            off = queue.popleft()
            if any(phi[a] + off[a] < rlo[a] or plo[a] + off[a] > rhi[a] for a in range(3)):
                path: list[int] = []
                while (step := parent[off]) is not None:
                    off, k = step
                    path.append(k)
                return _runs(path[::-1])
            for k, d in enumerate(ref.DIRECTIONS):
                nxt = ref.shift(off, d)
                if nxt not in parent and free(nxt):
                    parent[nxt] = (off, k)
                    queue.append(nxt)
        return None

    @staticmethod
    def interlocking(i: int, contacts: list[np.ndarray]) -> bool:
        """Whether A_i = [P1..Pi, R_i] is interlocking: on every axis the blocking graph over nodes 0..i-1
        (the pieces, 0 the key) and i (R_i) has one strongly connected component, or two with the key
        alone (`ref.is_interlocking`)."""
        for pairs in contacts:
            nodes = np.minimum(pairs, i + 1) - 1  # labels above i are R_i, node i
            edges = nodes[nodes[:, 0] != nodes[:, 1]]
            graph = csr_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(i + 1, i + 1))
            count, component = connected_components(graph, directed=True, connection="strong")
            if not (count == 1 or (count == 2 and int((component == component[0]).sum()) == 1)):
                return False
        return True


def verify_labels(labels: np.ndarray, removal: str = "straight") -> Verdict:
    """Every stage A_1..A_(K-1) of the assembly `labels`, in order, each through the checks in the order
    connected, removable, interlocking (docs/checkers.md): the first failure, or valid with each piece's
    moves out. The reference checkers' definition, computed once for all stages where it can be (the
    tests compare the verdicts, moves included, with the reference checkers applied stage by stage)."""
    if removal not in ref.REMOVAL_MODES:
        raise RLLockError(f"unknown removal mode {removal!r}: use one of {', '.join(ref.REMOVAL_MODES)}")
    labels = np.asarray(labels)
    k = validate_labels(labels)
    assembly = _Assembly.of(labels.astype(np.int64), k)
    sizes = [len(assembly.cells[j]) for j in range(1, k + 1)]
    rests = assembly.rests_connected()
    contacts = contact_pairs(assembly.labels)
    moves_of = assembly.straight_moves if removal == "straight" else assembly.path_moves
    disassembly = []
    for i in range(1, k):
        if not assembly.piece_connected(i) or not rests[i]:  # R_(K-1) is piece K
            return Verdict(False, k, removal, i, "connected", sizes)
        moves = moves_of(i)
        if moves is None:
            return Verdict(False, k, removal, i, "removable", sizes)
        if i >= 2 and not assembly.interlocking(i, contacts):
            return Verdict(False, k, removal, i, "interlocking", sizes)
        disassembly.append({"piece": i, "moves": [asdict(m) for m in moves]})
    return Verdict(True, k, removal, None, None, sizes, disassembly)
