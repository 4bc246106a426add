"""The reference checkers against the definitions themselves (brute force) on small cases."""

from __future__ import annotations

import numpy as np
from helpers import parts_after, random_valid_states, raw_chunks

from rllock.core import reference_checkers as ref
from rllock.core.env import make_task
from rllock.core.shapes import read_puz_labels


def _parts(labels: np.ndarray, upto: int) -> list[ref.Part]:
    parts = [frozenset(map(tuple, np.argwhere(labels == j).tolist())) for j in range(1, upto + 1)]
    return [*parts, frozenset(map(tuple, np.argwhere(labels > upto).tolist()))]


def test_scc_interlocking_agrees_with_subset_enumeration_on_published_stages(data):
    checked = 0
    for name in ("Cube_4x4x4_K9.puz", "Cube_4x4x4_K9_01.puz", "Cube_Hollow_4x4x4_K7.puz"):
        labels = read_puz_labels(data / "published" / name)
        for i in range(2, int(labels.max())):
            parts = _parts(labels, i)
            assert ref.is_interlocking(parts) == ref.is_interlocking_bruteforce(parts)
            checked += 1
    assert checked >= 15  # every stage i >= 2 of the three files


def test_scc_interlocking_agrees_with_subset_enumeration_on_random_states():
    """States reached through accepted chunks (interlocking) and the same states with one more raw,
    unchecked chunk (mostly not): both tests must agree on every one."""
    rng = np.random.default_rng(1)
    outcomes = {True: 0, False: 0}
    for shape, k in (("cube3", 5), ("box:4x3x2", 6), ("cube4", 8)):
        task = make_task(shape, k)
        for state in random_valid_states(task, rng, 6):
            for chunk in raw_chunks(task, state, rng, 4):
                parts, rest = parts_after(task, state, chunk)
                valid_state = [*parts[:-1], rest | parts[-1]]  # A_(i-1), before the chunk
                with_chunk = [*parts, rest]  # A_i with the unchecked chunk
                for assembly in (valid_state, with_chunk):
                    if len(assembly) < 3:
                        continue
                    expected = ref.is_interlocking_bruteforce(assembly)
                    assert ref.is_interlocking(assembly) == expected
                    outcomes[expected] += 1
    assert outcomes[False] > 20 and outcomes[True] > 20


def test_a_bar_of_three_unit_parts_is_not_interlocking():
    # A 3x1x1 bar split into three unit parts: the middle one is blocked on x by both neighbours,
    # but every part can slide along y and z, so nothing is interlocking.
    bar = [frozenset({(0, 0, 0)}), frozenset({(1, 0, 0)}), frozenset({(2, 0, 0)})]
    assert not ref.is_interlocking(bar)
    assert not ref.is_interlocking_bruteforce(bar)


def test_straight_removal_implies_path_removal():
    """Random pieces against random rests: every straight exit is a path exit, and both outcomes of
    each test occur (so the implication is exercised, not vacuous)."""
    rng = np.random.default_rng(0)
    seen = {"straight": 0, "path only": 0, "stuck": 0}
    for _ in range(400):
        cells = [tuple(v) for v in np.argwhere(rng.random((4, 4, 4)) < 0.7).tolist()]
        piece = frozenset(ref.sample_chunk({c: 0 for c in cells}, 1, 3, rng) or [])
        rest = frozenset(cells) - piece
        if not piece or not rest:
            continue
        straight, path = ref.straight_exit(piece, rest) is not None, ref.path_exit(piece, rest) is not None
        assert path or not straight
        seen["straight" if straight else "path only" if path else "stuck"] += 1
    assert min(seen.values()) > 0, seen


def test_path_removal_finds_a_two_move_exit_that_straight_misses():
    # The piece sits between two full layers (z = +-1); in its own layer it is walled on -x, +x, -y,
    # and on +y one voxel further away, so every straight ray is blocked, but one step along +y
    # opens a free row along +x.
    layers = {(x, y, z) for x in range(-2, 3) for y in range(-2, 3) for z in (-1, 1)}
    rest = frozenset(layers | {(-1, 0, 0), (1, 0, 0), (0, -1, 0), (0, 2, 0)})
    piece = frozenset({(0, 0, 0)})
    assert ref.straight_exit(piece, rest) is None
    moves = ref.path_exit(piece, rest)
    assert moves is not None and len(moves) >= 2
    assert moves[0] == ref.DIRECTION_NAMES.index("+y")
    assert not ref.is_removable(piece, rest | {(0, 1, 0)}, "path")
