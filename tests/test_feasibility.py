"""Tasks that provably have no assembly (rllock.core.feasibility) against exhaustive enumeration: on small
shapes, every stage-2 state A_2 = [P1, P2, R2] is tried with the reference checkers; the strands proof's
steps each against brute force."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from helpers import run_cli

from rllock.core import reference_checkers as ref
from rllock.core.env import make_task
from rllock.core.feasibility import _split_exists, _strand_length, held, impossibility
from rllock.core.topology import build_topology
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


def pegged(pegs: list[tuple[int, int, int]]) -> np.ndarray:
    """A 2x2x2 cube in a 4x4x4 canvas (voxels 1..2 on each axis) with single voxels stuck on its faces."""
    grid = np.zeros((4, 4, 4), dtype=bool)
    grid[1:3, 1:3, 1:3] = True
    for peg in pegs:
        grid[peg] = True
    return grid


PEGS_APART = pegged([(1, 1, 0), (2, 0, 2), (2, 2, 3), (0, 1, 2)])  # four pegs, no two within 2 steps
PEGS_THREE = pegged([(2, 0, 2), (2, 2, 3), (3, 2, 1)])


@pytest.mark.parametrize(
    "shape, pieces, removal",
    [
        (PEGS_APART, 3, "straight"),
        (PEGS_APART, 3, "path"),
        (PEGS_THREE, 3, "straight"),
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
    reason = impossibility(make_task(shape, pieces, removal))
    assert reason is not None and (isinstance(shape, str) or "tips of thin strands" in reason), reason
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


def _touches_six_ways(part: frozenset, cells: frozenset) -> bool:
    others = cells - part
    return all(any(ref.shift(v, d) in others for v in part) for d in ref.DIRECTIONS)


def _cells(grid: np.ndarray) -> frozenset:
    return frozenset(map(ref.voxel, np.argwhere(grid)))


def test_a_non_key_part_of_an_interlocking_state_touches_the_rest_six_ways():
    # The strands proof's first step, against the definition itself: in every stage A_i (i >= 2) of
    # assemblies the solver finds on a cube with pegs, which the brute-force definition calls
    # interlocking, every part but the key touches the others towards all 6 directions.
    grid = np.zeros((6, 6, 6), dtype=bool)
    grid[1:5, 1:5, 1:5] = True
    grid[0, 1, 1] = grid[5, 4, 4] = grid[2, 0, 3] = True
    cells = _cells(grid)
    stages = 0
    for pieces, seed in ((5, 0), (6, 0), (7, 1)):
        (labels,) = solve(make_task(grid, pieces), count=1, time_limit=60, seed=seed)
        part = [frozenset(map(ref.voxel, np.argwhere(labels == k))) for k in range(1, pieces + 1)]
        for i in range(2, pieces):
            parts = [*part[:i], frozenset().union(*part[i:])]
            assert ref.is_interlocking_bruteforce(parts)
            assert all(_touches_six_ways(p, cells) for p in parts[1:])
            stages += 1
    assert stages == 3 + 4 + 5


def _sets_with(cells: frozenset, t: tuple, size: int) -> list[frozenset]:
    return [s for s in _pieces(cells, size) if t in s]


def test_held_is_whether_some_connected_set_around_the_voxel_touches_the_rest_six_ways():
    answers = set()
    for grid in (pegged([(1, 1, 0), (2, 0, 2), (3, 2, 1)]), np.ones((3, 2, 2), dtype=bool)):
        topology = build_topology(grid)
        cells = _cells(grid)
        for t, xyz in enumerate(topology.coords):
            for size in (2, 3, 4, 5):
                expected = any(_touches_six_ways(s, cells) for s in _sets_with(cells, ref.voxel(xyz), size))
                assert held(topology.nbr, t, size) is expected, (xyz, size)
                answers.add(expected)
    assert answers == {True, False}
    # Out of budget: no answer, never a wrong one.
    topology = build_topology(np.ones((4, 4, 4), dtype=bool))
    assert held(topology.nbr, 0, 12, budget=5) is None


def test_a_strands_length_and_a_piece_with_two_tips_holds_both_strands():
    spider = make_task("spider", 20).topology
    tips = np.flatnonzero((spider.nbr >= 0).sum(axis=1) == 1)
    assert sorted(_strand_length(spider.nbr, int(t)) for t in tips) == [5, 5, 5, 5, 7, 7, 7, 7]
    # Two 2-voxel strands on a 2x2x2 cube, by brute force: every connected set holding both tips holds
    # both strands whole, so it has at least 4 voxels.
    grid = np.zeros((6, 4, 4), dtype=bool)
    grid[2:4, 1:3, 1:3] = True
    grid[0:2, 1, 1] = grid[4:6, 2, 2] = True
    topology = build_topology(grid)
    tips = [int(t) for t in np.flatnonzero((topology.nbr >= 0).sum(axis=1) == 1)]
    assert [_strand_length(topology.nbr, t) for t in tips] == [2, 2]
    a, b = (ref.voxel(topology.coords[t]) for t in tips)
    strands = {a, (1, 1, 1), b, (4, 2, 2)}
    both = [s for size in range(2, 9) for s in _pieces(_cells(grid), size) if a in s and b in s]
    assert both and all(strands <= s for s in both)
    assert _strand_length(build_topology(np.ones((5, 1, 1), dtype=bool)).nbr, 0) == 1  # a rod: no bound


def _fits(chosen: list[int], size: int, steps: np.ndarray, strands: list[int]) -> bool:
    """Whether one piece of `size` voxels may hold the tips `chosen`: within size - 1 steps of one another
    and, two or more, their strands within `size` voxels."""
    pairs = itertools.combinations(chosen, 2)
    return len(chosen) < 2 or (
        all(steps[j, k] <= size - 1 for j, k in pairs) and sum(strands[j] for j in chosen) <= size
    )


def test_the_split_between_key_and_last_piece_is_the_brute_force_over_every_assignment():
    rng = np.random.default_rng(0)
    answers = set()
    for _ in range(300):
        count = int(rng.integers(2, 7))
        steps = rng.integers(1, 15, size=(count, count))
        steps = np.triu(steps, 1) + np.triu(steps, 1).T
        strands = [int(x) for x in rng.integers(1, 6, size=count)]
        n = int(rng.integers(3, 12))
        last = n + int(rng.integers(0, 10))
        key_only = [bool(x) for x in rng.random(count) < 0.2]

        expected = any(
            _fits([j for j in range(count) if key[j]], n, steps, strands)
            and _fits([j for j in range(count) if not key[j]], last, steps, strands)
            and all(key[j] for j in range(count) if key_only[j])
            for key in itertools.product([True, False], repeat=count)
        )
        answers.add(expected)
        assert _split_exists(steps, strands, n, last, key_only) is expected
    assert answers == {True, False}


def test_spider_k20_and_k30_have_no_assembly_its_legs_only_the_key_and_last_piece_can_hold():
    for pieces in (20, 30):
        reason = impossibility(make_task("spider", pieces))
        assert reason is not None and "tips of thin strands" in reason, reason
    # K = 15 and 16 have assemblies (the solver finds them, docs/results.md); K = 19 has no proof.
    assert all(impossibility(make_task("spider", k)) is None for k in (15, 16, 19))
    code, _, err = run_cli("solve", "--shape", "spider", "--pieces", "20", "--out", "/nonexistent/never")
    assert code == 2 and len(err.strip().splitlines()) == 1 and "n = 10 voxels" in err, err
    # The advice names the largest K below that no proof refuses (19 has no proof, above).
    assert "the largest smaller K it leaves open is 19" in err, err
