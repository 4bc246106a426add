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

tests/test_feasibility.py checks both against exhaustive enumeration of small shapes with the reference
checkers.
"""

from __future__ import annotations

import numpy as np

from rllock.core.env import Task
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
    return None


def check_feasible(task: Task) -> None:
    """Raise a one-line error when `task` provably has no valid assembly (`impossibility`)."""
    reason = impossibility(task)
    if reason is not None:
        raise RLLockError(
            f"{task.shape_name} K={task.pieces} ({task.removal} removal) cannot have a valid assembly: "
            + reason
        )
