"""Tasks that provably have no valid assembly: told at once, instead of searched for the whole time limit.

Both conditions concern stage 2, A_2 = [P1, P2, R2], which every task with K >= 3 must pass (R2 is not
empty then), and its interlocking check: on each axis the directional blocking graph (p -> q when a voxel
of p has a voxel of q next to it towards +axis) has one strongly connected component, or two of which one
is the key P1 alone.

- **One voxel thick.** When the shape has extent 1 along an axis, no two voxels are neighbours along it:
  that axis's graph has no edge, so P1, P2 and R2 are three components. Any removal mode.
- **Single voxels, straight removal.** With n = 1, P2 is one voxel v that slides out of [P2, R2] along
  some direction d, so no voxel of R2 lies on the ray from v along d. Take d as +axis (the graph for -d
  is the transpose, with the same components). P2's only out-edge goes to the part at v + d, which is P1
  (one voxel) or nothing; P1's only out-edge goes to the part at v + 2d, on the same ray, so neither R2
  nor P2. So P2 never reaches R2: neither one component nor {P2, R2} with the key alone.

- **Strands only the key and the last piece can hold** (any removal mode). Every part of A_i but the key
  has, on each axis, an out-edge and an in-edge (one strongly connected component, or two with the key
  alone, of at least 3 parts): a voxel with a voxel of another part next to it towards each of the 6
  directions. For 2 <= i <= K-1, A_i holds the whole shape, so Pi (n voxels) touches the rest of the
  shape in all 6 directions, and so does the last piece R_(K-1) (m = N - (K-1)n voxels) in A_(K-1). A
  tip (a voxel with one neighbour) that no connected set of n voxels containing it can hold that way
  (`held`, by enumerating those sets: a spider's foot at the end of its leg) lies in P1 or in the last
  piece, and in P1 if no set of m voxels can hold it either. Two voxels of a connected piece of s voxels
  are at most s - 1 steps apart inside the shape, and a piece with two tips holds both their strands
  whole (a tip's strand: it and the voxels of two neighbours that lead from it to the first voxel with
  more), so their lengths add up to at most s. When no split of those tips between P1 and the last
  piece meets these bounds (`_split_exists`), there is no assembly.

tests/test_feasibility.py checks each against exhaustive enumeration of small shapes with the reference
checkers.
"""

from __future__ import annotations

from collections import deque
from dataclasses import replace
from functools import lru_cache

import numpy as np

from rllock.core.env import Task
from rllock.core.topology import Topology
from rllock.errors import RLLockError

AXES = "xyz"


def impossibility(task: Task) -> str | None:
    """Why `task` has no valid assembly, when one of the module's proofs applies; else None."""
    if task.pieces < 3:
        return None
    filled = np.argwhere(task.topology.grid)
    extent = filled.max(axis=0) - filled.min(axis=0) + 1
    thin = [AXES[a] for a in range(3) if extent[a] == 1]
    if thin:
        return (
            f"the shape is one voxel thick along {thin[0]}, so no piece can be held along {thin[0]}: "
            "only K = 2 has an assembly there"
        )
    if task.piece_size == 1 and task.removal == "straight":
        return (
            f"its pieces would be single voxels (n = N/K = {task.size}/{task.pieces} < 2), and under "
            "straight removal the others cannot hold a single-voxel piece: "
            f"use K <= {task.size // 2} or --removal path"
        )
    unheld = _strands_unheld(task)
    if unheld:
        corner = tuple(int(c) for c in task.topology.coords[unheld[0]])
        return (
            f"{len(unheld)} voxels at the tips of thin strands (one at {corner}) cannot be held in place by "
            f"any piece of n = {task.piece_size} voxels, so only the key and the last piece could take them, "
            "and those two cannot take them all: use fewer, larger pieces"
        )
    return None


def _largest_open_below(task: Task, span: int = 50) -> int | None:
    """The largest K below `task.pieces` (at most `span` below) that the strands proof leaves open, for
    the advice of a refusal: asked only where a message is shown, as it runs the proof up to `span`
    times."""
    return next(
        (
            k
            for k in range(task.pieces - 1, max(2, task.pieces - span), -1)
            if not _strands_unheld(replace(task, pieces=k))
        ),
        None,
    )


def _strands_unheld(task: Task) -> list[int]:
    return _unheld_tips(task.topology, task.piece_size, task.last_size)


HELD_BUDGET = 20_000  # sets enumerated per voxel; past it the voxel counts as held (no proof from it)
TIPS_BUDGET = 400_000  # sets enumerated for all tips together: shapes with thousands of tips share it
HELD_MAX_SIZE = 64  # pieces larger than this are not enumerated (no proof from them)
MAX_TIPS = 64  # tips split between P1 and the last piece (a proof on some of them is a proof)


def held(nbr: np.ndarray, t: int, size: int, budget: int = HELD_BUDGET) -> bool | None:
    """Whether some connected set of `size` voxels containing voxel `t` has, towards each of the 6
    directions, a voxel whose neighbour there is a shape voxel outside the set (True), none has (False),
    or the `budget` of sets ran out first (None). Each connected set containing `t` is enumerated once:
    a voxel taken from the extension set is either added (its new neighbours join the extension) or
    excluded for good."""
    if size >= nbr.shape[0] or size > HELD_MAX_SIZE:
        return None
    inside = np.zeros(nbr.shape[0], dtype=bool)
    inside[t] = True
    members = [t]
    left = [budget]

    def touches_all_ways() -> bool:
        return all(any(0 <= (u := nbr[v, d]) and not inside[u] for v in members) for d in range(6))

    def grow(extension: list[int], seen: set[int]) -> bool | None:
        left[0] -= 1
        if left[0] < 0:
            return None
        if len(members) == size:
            return touches_all_ways()
        extension, seen = list(extension), set(seen)
        while extension:
            v = extension.pop()
            fresh = [int(u) for u in nbr[v] if u >= 0 and u not in seen]
            inside[v] = True
            members.append(v)
            found = grow(extension + fresh, seen | set(fresh))
            members.pop()
            inside[v] = False
            if found is not False:
                return found
        return False

    first = [int(u) for u in nbr[t] if u >= 0]
    return grow(first, {t, *first})


@lru_cache(maxsize=32)
def _unheld_tips(topology: Topology, n: int, last: int) -> list[int]:
    """The tips (voxels with one neighbour) that only P1 or the last piece can hold (`held` at n is
    False), when no split of them between those two meets the bounds of the module docstring
    (`_split_exists`); else []."""
    nbr = topology.nbr
    tips = np.flatnonzero((nbr >= 0).sum(axis=1) == 1)
    budget = min(HELD_BUDGET, TIPS_BUDGET // max(len(tips), 1))
    only = [int(t) for t in tips if held(nbr, int(t), n, budget) is False][:MAX_TIPS]
    if len(only) < 2:
        return []
    key_only = [held(nbr, t, last, budget) is False for t in only] if last != n else [True] * len(only)
    steps = np.array([_steps_from(nbr, t)[only] for t in only])
    strands = [_strand_length(nbr, t) for t in only]
    return [] if _split_exists(steps, strands, n, last, key_only) else only


def _steps_from(nbr: np.ndarray, source: int) -> np.ndarray:
    """Steps from `source` to every voxel inside the shape (breadth-first)."""
    steps = np.full(nbr.shape[0], -1, dtype=np.int64)
    steps[source] = 0
    queue = deque([source])
    while queue:
        v = queue.popleft()
        for u in nbr[v]:
            if u >= 0 and steps[u] < 0:
                steps[u] = steps[v] + 1
                queue.append(int(u))
    return steps


def _strand_length(nbr: np.ndarray, tip: int) -> int:
    """How many voxels the strand from `tip` has: it and the voxels of two neighbours that follow, up to
    the first voxel with three or more; 1 (no bound from it) when the shape is one strand end to end."""
    previous, v, length = -1, tip, 1
    while True:
        (following,) = [int(u) for u in nbr[v] if u >= 0 and u != previous][:1] or [-1]
        degree = int((nbr[following] >= 0).sum()) if following >= 0 else 0
        if degree <= 1:
            return 1
        if degree > 2:
            return length
        previous, v, length = v, following, length + 1


SPLITS_TRIED = 100_000  # past this many sets for P1, a split counts as found (no proof)


def _split_exists(steps: np.ndarray, strands: list[int], n: int, last: int, key_only: list[bool]) -> bool:
    """Whether tips `steps` apart (a square matrix), with strands of `strands` voxels, can be split between
    P1 (n voxels) and the last piece (`last` voxels), those marked `key_only` in P1: the tips of one piece
    within s - 1 steps of one another and, two or more, their strands within s voxels. Every set P1 can
    take (those within its bounds that hold every `key_only` tip) is tried against the rest."""
    count = len(strands)
    tried = [0]

    def fits(chosen: list[int], size: int) -> bool:
        if len(chosen) < 2:
            return True
        near = all(steps[j, k] <= size - 1 for i, j in enumerate(chosen) for k in chosen[i + 1 :])
        return near and sum(strands[j] for j in chosen) <= size

    def extend(j: int, key: list[int]) -> bool:
        tried[0] += 1
        if tried[0] > SPLITS_TRIED:
            return True
        if j == count:
            return fits([k for k in range(count) if k not in key], last)
        if fits([*key, j], n) and extend(j + 1, [*key, j]):
            return True
        return not key_only[j] and extend(j + 1, key)

    return extend(0, [])


def check_feasible(task: Task) -> None:
    """Raise a one-line error when `task` provably has no valid assembly (`impossibility`)."""
    reason = impossibility(task)
    if reason is None:
        return
    fewer = _largest_open_below(task) if _strands_unheld(task) else None
    raise RLLockError(
        f"{task.shape_name} K={task.pieces} ({task.removal} removal) cannot have a valid assembly: "
        + reason
        + (f" (the largest smaller K it leaves open is {fewer})" if fewer else "")
    )
