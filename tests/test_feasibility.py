"""Tasks that provably have no assembly (rllock.core.feasibility) against exhaustive enumeration: on small
shapes, every stage-2 state A_2 = [P1, P2, R2] is tried with the reference checkers."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from helpers import run_cli

from rllock.core import reference_checkers as ref
from rllock.core.env import make_task
from rllock.core.feasibility import impossibility
from rllock.errors import RLLockError
from rllock.search.solver import solve


def _pieces(cells: frozenset, n: int) -> list[frozenset]:
    """Every connected set of n voxels among `cells`."""
    return [frozenset(c) for c in itertools.combinations(sorted(cells), n) if ref.is_connected(c)]


def stage_two_valid(cells: frozenset, p1: frozenset, p2: frozenset, removal: str) -> bool:
    """Whether A_1 = [P1, R1] and A_2 = [P1, P2, R2] pass every check of the reference checkers."""
    r1 = cells - p1
    r2 = r1 - p2
    return (
        ref.is_connected(p1)
        and ref.is_connected(p2)
        and ref.is_connected(r1)
        and ref.is_removable(p1, r1, removal)
        and ref.is_connected(r2)
        and ref.is_removable(p2, r2, removal)
        and ref.is_interlocking([p1, p2, r2])
    )


def stage_two_states(shape: str, pieces: int, removal: str) -> int:
    """How many (P1, P2) make A_1 and A_2 valid, by brute force over every pair of connected pieces."""
    task = make_task(shape, pieces, removal)
    cells = frozenset(map(ref.voxel, np.argwhere(task.topology.grid)))
    n = task.piece_size
    return sum(
        stage_two_valid(cells, p1, p2, removal) for p1 in _pieces(cells, n) for p2 in _pieces(cells - p1, n)
    )


@pytest.mark.parametrize(
    "shape, pieces, removal",
    [
        ("box:3x3x1", 3, "straight"),
        ("box:3x3x1", 3, "path"),
        ("box:4x2x1", 4, "path"),
        ("box:1x3x3", 4, "straight"),
        ("cube2", 5, "straight"),
        ("box:3x2x2", 7, "straight"),
        ("box:3x3x2", 12, "straight"),
    ],
)
def test_every_task_called_impossible_has_no_valid_stage_two(shape, pieces, removal):
    assert impossibility(make_task(shape, pieces, removal)) is not None
    assert stage_two_states(shape, pieces, removal) == 0


def test_the_enumeration_accepts_a_real_assembly_and_k2_on_a_flat_shape_is_allowed():
    task = make_task("cube4", 7)
    assert impossibility(task) is None and impossibility(make_task("box:3x3x1", 2)) is None
    (labels,) = solve(task, count=1, time_limit=60, seed=0)
    cells = frozenset(map(ref.voxel, np.argwhere(labels > 0)))
    piece = {k: frozenset(map(ref.voxel, np.argwhere(labels == k))) for k in (1, 2)}
    assert stage_two_valid(cells, piece[1], piece[2], "straight")


def test_an_impossible_task_is_one_line_and_exit_2_at_once():
    code, _, err = run_cli(
        "solve", "--shape", "cube4", "--pieces", "64", "--out", "/nonexistent/never", timeout=60
    )
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "single voxels" in err and "K <= 32" in err
    code, _, err = run_cli("solve", "--shape", "box:6x5x1", "--pieces", "5", "--out", "/nonexistent/never")
    assert code == 2 and "one voxel thick along z" in err, err
    code, _, err = run_cli("train", "--shape", "box:6x5x1", "--pieces", "5", "--logdir", "/nonexistent/never")
    assert code == 2 and "one voxel thick along z" in err and len(err.strip().splitlines()) == 1, err
    code, _, err = run_cli(
        "generate", "--checkpoint", "general", "--shape", "cube4", "--pieces", "64", "--out", "x"
    )
    assert code == 2 and "single voxels" in err, err
    with pytest.raises(RLLockError, match="one voxel thick along x"):
        solve(make_task("box:1x4x4", 3), time_limit=60)
