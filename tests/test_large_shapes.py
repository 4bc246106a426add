"""The closed proposal (`compiled_sampler`) and the solver on large shapes (issue 23).

The closed proposal grows chunks that slide out of the remaining volume along one direction; the
checkers still decide. These tests check its chunks against the plain reference and a brute-force
enumeration, that the default (frontier) sampler's random stream is unchanged, and that the solver with
the proposal finds a verified assembly where frontier growth alone finds none in the same budget.
"""

from __future__ import annotations

import hashlib
import itertools

import numpy as np
import pytest
from helpers import random_valid_states

from rllock.core import compiled_checkers as checkers
from rllock.core import compiled_sampler as sampler
from rllock.core import reference_checkers as ref
from rllock.core.env import initial_state, make_task, sample_accepted, tightest_subset
from rllock.core.verifier import verify_labels
from rllock.search.dfs import expand
from rllock.search.search_config import SearchConfig
from rllock.search.solver import search, solve


def _cells(task, voxels) -> frozenset[ref.Voxel]:
    return frozenset(ref.voxel(task.topology.coords[v]) for v in voxels)


def _slides_out(piece: frozenset[ref.Voxel], rest: frozenset[ref.Voxel], d: int, reach: int) -> bool:
    """Brute force: no voxel of `piece`, moved 1..reach steps along direction d, lands in `rest`."""
    step = ref.DIRECTIONS[d]
    return all(ref.shift(v, step, t) not in rest for v in piece for t in range(1, reach + 1))


@pytest.mark.parametrize(
    "shape,k", [("cube4", 4), ("cube5", 6), ("box:6x4x3", 5), ("ring", 8), ("desia-dog", 40)]
)
def test_closed_chunks_are_connected_remaining_n_voxels_that_slide_out_along_their_direction(shape, k):
    task = make_task(shape, k)
    n, reach = task.piece_size, max(task.topology.dims)
    rng = np.random.default_rng(k)
    checked = 0
    for state in itertools.islice(random_valid_states(task, rng, 2), 12):
        chunks, dirs = sampler.sample_raw_closed(
            task.topology.arrays, state.labels, state.placed + 1, n, 40, int(rng.integers(1 << 30))
        )
        rest_before = np.flatnonzero(state.labels == 0)
        for chunk, d in zip(chunks, dirs):
            assert len(set(chunk.tolist())) == n
            assert set(chunk.tolist()) <= set(rest_before.tolist())
            piece = _cells(task, chunk)
            rest = _cells(task, np.setdiff1d(rest_before, chunk))
            assert ref.is_connected(piece)
            assert _slides_out(piece, rest, int(d), reach)
            assert ref.is_removable(piece, rest, "straight")
            checked += 1
    assert checked >= 100


def test_closed_chunks_are_exactly_the_closed_connected_chunks_a_brute_force_finds():
    """On a tiny box every connected n-voxel subset of R that holds a seed voxel (one touching the last
    piece) and slides out along d is enumerated; the proposal draws those and nothing else."""
    task = make_task("box:3x3x2", 3)
    n, reach = task.piece_size, max(task.topology.dims)
    state = initial_state(task)
    first = [0, 1, 2, 3, 4, 5]  # the 1x3x2 slab at x = 0 (voxels are numbered in x, y, z order)
    assert n == 6 and ref.is_connected(_cells(task, first))
    after = state.labels.copy()
    after[first] = 1
    for piece, labels in ((1, state.labels), (2, after)):
        rest = np.flatnonzero(labels == 0)
        nbr = task.topology.nbr
        seeds = {v for v in rest if piece == 1 or any(u >= 0 and labels[u] == piece - 1 for u in nbr[v])}
        expected = set()
        for subset in itertools.combinations(rest.tolist(), n):
            cells = _cells(task, subset)
            if not seeds & set(subset) or not ref.is_connected(cells):
                continue
            others = _cells(task, np.setdiff1d(rest, subset))
            for d in range(6):
                if _slides_out(cells, others, d, reach):
                    expected.add((subset, d))
        chunks, dirs = sampler.sample_raw_closed(task.topology.arrays, labels, piece, n, 1_500_000, 3)
        rows = np.unique(np.column_stack([np.sort(chunks, axis=1), dirs]), axis=0)
        drawn = {(tuple(row[:-1].tolist()), int(row[-1])) for row in rows}
        assert drawn <= expected
        assert len(drawn) == len(expected) > 10


@pytest.mark.parametrize("removal", ["straight", "path"])
def test_mixed_sampler_keeps_exactly_the_checker_accepted_raw_chunks(removal):
    """With every chunk from the closed proposal, sample_and_check_mixed draws the stream of
    sample_raw_closed and keeps exactly what the full checks accept; with none it is sample_and_check."""
    task = make_task("desia-dog", 30, removal)
    topo, n = task.topology.arrays, task.piece_size
    rng = np.random.default_rng(5)
    kept_total = 0
    for state in itertools.islice(random_valid_states(task, rng, 1), 0, 12, 3):
        piece, seed = state.placed + 1, int(rng.integers(1 << 30))
        raw, _ = sampler.sample_raw_closed(topo, state.labels, piece, n, 300, seed)
        bits = checkers.check_chunks(topo, state.labels, piece, raw, removal == "path")
        kept, _ = sampler.sample_and_check_mixed(
            topo, state.labels, piece, n, 300, removal == "path", seed, 1.0
        )
        np.testing.assert_array_equal(kept, raw[bits == checkers.ALL_CHECKS])
        kept_total += len(kept)
        plain, _ = sampler.sample_and_check(topo, state.labels, piece, n, 300, removal == "path", seed)
        same, _ = sampler.sample_and_check_mixed(
            topo, state.labels, piece, n, 300, removal == "path", seed, 0.0
        )
        np.testing.assert_array_equal(plain, same)
    assert kept_total > 0


def _default_stream_digest() -> str:
    h = hashlib.sha256()
    for shape, k in [("cube5", 13), ("desia-bunny", 30)]:
        task = make_task(shape, k)
        topo, n = task.topology.arrays, task.piece_size
        labels = np.zeros(task.size, np.int16)
        for piece in (1, 2, 3):
            raw = sampler.sample_raw(topo, labels, piece, n, 200, 7 * piece)
            acc, _ = sampler.sample_and_check(topo, labels, piece, n, 400, False, 7 * piece)
            out, found, drawn = sampler.candidates_serial(
                topo, labels[None], np.array([piece]), np.array([11 * piece]), n, 1024, 16, False
            )
            for a in (raw, acc, out, found, drawn):
                h.update(np.ascontiguousarray(a).astype(np.int64).tobytes())
            if len(acc) == 0:
                break
            labels = labels.copy()
            labels[acc[0]] = piece
    return h.hexdigest()


def test_default_sampler_stream_is_unchanged():
    """The frontier sampler that MCTS and the shipped networks use draws what it drew before the closed
    proposal existed (digest computed with the sampler of commit HEAD before issue 23's change)."""
    assert _default_stream_digest() == GOLDEN_DEFAULT_DIGEST


GOLDEN_DEFAULT_DIGEST = "a7cae8d25c7457800a245eecfd509ea7544bd49d1c42b078b1fa70c466b499a0"


def test_closed_proposal_solves_a_task_frontier_growth_misses():
    """desia-bunny (966 voxels) K=30, n=32: frontier chunks of 32 voxels are almost never removable."""
    task = make_task("desia-bunny", 30)
    old = SearchConfig(closed_share=0.0, restart_per_piece=0, deep_from=10**6)
    assert next(iter(search(task, seed=0, time_limit=8, config=old)), None) is None
    found = solve(task, time_limit=30, seed=0, config=SearchConfig())
    assert len(found) == 1
    labels = found[0]
    sizes = np.bincount(labels.ravel())[1:]
    assert len(sizes) == 30 and (sizes[:-1] == 32).all()
    assert verify_labels(labels, "straight").valid


def test_remainder_growth_is_the_cut_or_the_change_of_the_remaining_volumes_surface():
    """Against a brute force over voxel coordinates, on random states and raw chunks of several shapes:
    with `outside` 0 the faces a chunk shares with the rest of R; with 1, how much R's surface (its
    faces to anything not in R) grows when the chunk leaves it."""
    checked = 0
    for shape, k in [("cube5", 6), ("ring", 8), ("desia-dog", 40)]:
        task = make_task(shape, k)
        coords = [tuple(c) for c in task.topology.coords.tolist()]
        rng = np.random.default_rng(k)
        for state in itertools.islice(random_valid_states(task, rng, 1), 0, 12, 3):
            raw = sampler.sample_raw(
                task.topology.arrays,
                state.labels,
                state.placed + 1,
                task.piece_size,
                20,
                int(rng.integers(1 << 30)),
            )
            nbr = task.topology.arrays[0]
            cuts = sampler.remainder_growth(nbr, state.labels, raw, 0)
            growths = sampler.remainder_growth(nbr, state.labels, raw, 1)
            rest = {coords[v] for v in np.flatnonzero(state.labels == 0)}
            for chunk, cut, growth in zip(raw, cuts, growths):
                piece = {coords[v] for v in chunk}
                faces = sum(
                    (x + dx, y + dy, z + dz) in rest - piece
                    for x, y, z in piece
                    for dx, dy, dz in ref.DIRECTIONS
                )
                assert cut == faces
                assert growth == _surface(rest - piece) - _surface(rest)
                checked += 1
    assert checked >= 100


def _surface(voxels: set) -> int:
    return sum((x + dx, y + dy, z + dz) not in voxels for x, y, z in voxels for dx, dy, dz in ref.DIRECTIONS)


def test_tightest_children_are_distinct_accepted_chunks_with_the_least_growth_or_cut():
    task = make_task("desia-dog", 40)
    rng = np.random.default_rng(2)
    for state in itertools.islice(random_valid_states(task, rng, 1), 0, 20, 5):
        accepted = sample_accepted(task, state, seed=int(rng.integers(1 << 30)), num_samples=400)
        if len(accepted) < 12:
            continue
        unique = {tuple(sorted(c)) for c in accepted.tolist()}
        every = np.array(sorted(unique), np.int32)
        for surface in (False, True):
            kids = tightest_subset(task, state, accepted, 8, seed=3, surface=surface)
            assert len({tuple(c) for c in kids.tolist()}) == len(kids) == min(8, len(unique))
            assert {tuple(c) for c in kids.tolist()} <= unique
            growth = sampler.remainder_growth(task.topology.arrays[0], state.labels, every, int(surface))
            kid_growth = sampler.remainder_growth(task.topology.arrays[0], state.labels, kids, int(surface))
            assert kid_growth.max() <= np.sort(growth)[len(kids) - 1]


def test_by_default_straight_removal_judges_by_the_surface_and_path_removal_as_before():
    straight, path = make_task("cube4", 8), make_task("box:6x5x4", 12, "path")
    default = SearchConfig()
    assert default.surface(straight) and default.by_remainder(straight, default.order_within)
    assert not default.by_remainder(straight, default.order_within + 1)
    assert not default.surface(path) and not default.by_remainder(path, 0)
    assert SearchConfig(remainder="surface").surface(path)
    assert not SearchConfig(remainder="cut").surface(straight)
    assert SearchConfig(child_order="remainder").by_remainder(path, 0)
    assert not SearchConfig(child_order="count").by_remainder(straight, 0)
    assert not SearchConfig(deep_from=30).by_remainder(straight, 0)  # out of deep mode: no such order


def test_children_are_tried_least_growth_first_near_the_end_else_most_continuations_first():
    """Pop order, best last: in the order of the remainder's judgement at nodes with at most
    `order_within` pieces left, else (or with `child_order="count"`) by the lookahead's count. Either
    way each child has a continuation."""
    task = make_task("desia-dog", 40)
    nbr = task.topology.arrays[0]
    rng = np.random.default_rng(5)
    tried = 0
    configs = {
        "remainder": SearchConfig(child_order="remainder", order_within=task.pieces),
        "count": SearchConfig(child_order="count"),
        "beyond": SearchConfig(child_order="remainder", order_within=0),
    }
    for state in itertools.islice(random_valid_states(task, rng, 3), 1, 40, 5):
        for name, config in configs.items():
            kids = expand(task, state, seed=7, config=config)
            assert all(k.grand is not None and len(k.grand) for k in kids)
            if name != "remainder":
                assert [k.share for k in kids] == sorted(k.share for k in kids)
                continue
            chunks = np.array([np.flatnonzero(k.state.labels == k.state.placed) for k in kids], np.int32)
            growth = sampler.remainder_growth(nbr, state.labels, chunks, 1).tolist()
            assert growth == sorted(growth, reverse=True)
            tried += len(kids) > 2 and growth != sorted(growth)
    assert tried  # nodes where the two orders differ


def _accepted_with(task, state, seed, **options):
    topo = task.topology.arrays
    return sampler.sample_and_check_mixed(
        topo, state.labels, state.placed + 1, task.piece_size, 400, False, seed, 0.0, **options
    )[0]


def test_thin_and_wide_growth_keep_only_checker_accepted_chunks_and_change_what_is_drawn():
    """Thin growth prefers frontier voxels with fewer remaining neighbours; wide seeds start chunks at
    any remaining voxel that touches a placed piece, not only the previous one. Every chunk kept still
    passes all three checks, and neither option changes the default stream when off."""
    task = make_task("desia-dog", 40)
    topo, nbr = task.topology.arrays, task.topology.arrays[0]
    rng = np.random.default_rng(4)
    degrees: dict[int, list[int]] = {0: [], 1: []}
    away = 0
    for state in itertools.islice(random_valid_states(task, rng, 2), 1, None, 2):
        piece, seed = state.placed + 1, int(rng.integers(1 << 30))
        plain, _ = sampler.sample_and_check(topo, state.labels, piece, task.piece_size, 400, False, seed)
        np.testing.assert_array_equal(_accepted_with(task, state, seed, thin=0, wide_seeds=False), plain)
        free = state.labels == 0
        for thin in (0, 1):
            for chunk in _accepted_with(task, state, seed, thin=thin):
                degrees[thin] += [sum(free[u] for u in nbr[v] if u >= 0) for v in chunk]
        wide = _accepted_with(task, state, seed, wide_seeds=True)
        if len(wide):
            bits = checkers.check_chunks(topo, state.labels, piece, wide, False)
            assert (bits == checkers.ALL_CHECKS).all()
            previous = state.labels == piece - 1
            away += sum(not previous[nbr[chunk]].any() for chunk in wide)
    assert np.mean(degrees[1]) < np.mean(degrees[0]) - 0.1
    assert away > 0


def test_deep_mode_solves_many_small_pieces_where_the_plain_search_gets_stuck():
    """mario (548 voxels, 4 thick) in K=50 pieces of 10: the plain search strands what remains (none
    in 300 s in docs/notebook/benchmarks.md); deep mode keeps it compact (0.5 s there)."""
    task = make_task("mario", 50)
    plain = SearchConfig(deep_from=10**6)
    assert not plain.deep(task) and SearchConfig().deep(task)
    assert next(iter(search(task, seed=0, time_limit=4, config=plain)), None) is None
    found = solve(task, time_limit=60, seed=0)
    assert len(found) == 1 and verify_labels(found[0], "straight").valid
    assert len(np.unique(found[0])) == 51  # 50 pieces and the empty cells
