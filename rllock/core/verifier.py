"""The full verifier: every stage A_1..A_(K-1) of an assembly through the reference checkers.

Labels are an int grid `[x, y, z]`: 0 empty, 1..K the piece ids in disassembly order (1 = key).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from rllock.core import reference_checkers as ref
from rllock.errors import RLLockError

CHECKER_VERSION = "1"
CHECKER_NAME = "rllock.core.verifier (reference checkers, docs/checkers.md)"


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


def removal_moves(piece: ref.Part, rest: ref.Part, removal: str) -> list[Move] | None:
    """The moves that take `piece` out of `rest`'s bounding box, or None if it cannot leave."""
    if removal == "straight":
        exit_ = ref.straight_exit(piece, rest)
        return None if exit_ is None else [Move(ref.DIRECTION_NAMES[exit_[0]], exit_[1])]
    path = ref.path_exit(piece, rest)
    return None if path is None else _runs(path)


def _check_stage(parts: list[ref.Part], rest: ref.Part, removal: str) -> tuple[str | None, list[Move]]:
    """The first failing check of A_i = [P1..Pi, Ri] in the order connected, removable, interlocking
    (None when valid), and Pi's removal moves."""
    if not all(ref.is_connected(p) for p in parts) or not ref.is_connected(rest):
        return "connected", []
    moves = removal_moves(parts[-1], rest, removal)
    if moves is None:
        return "removable", []
    if len(parts) >= 2 and not ref.is_interlocking([*parts, rest]):
        return "interlocking", []
    return None, moves


def verify_labels(labels: np.ndarray, removal: str = "straight") -> Verdict:
    if removal not in ref.REMOVAL_MODES:
        raise RLLockError(f"unknown removal mode {removal!r}: use one of {', '.join(ref.REMOVAL_MODES)}")
    labels = np.asarray(labels)
    k = validate_labels(labels)
    cells = {j: frozenset(ref.voxel(v) for v in np.argwhere(labels == j)) for j in range(1, k + 1)}
    sizes = [len(cells[j]) for j in range(1, k + 1)]
    disassembly = []
    for i in range(1, k):
        parts = [cells[j] for j in range(1, i + 1)]
        rest = frozenset().union(*(cells[j] for j in range(i + 1, k + 1)))
        failed, moves = _check_stage(parts, rest, removal)
        if failed is not None:
            return Verdict(False, k, removal, i, failed, sizes)
        disassembly.append({"piece": i, "moves": [asdict(m) for m in moves]})
    return Verdict(True, k, removal, None, None, sizes, disassembly)
