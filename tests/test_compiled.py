"""The compiled sampler and checkers against the reference implementation."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import parts_after, random_valid_states, raw_chunks, reference_bits, voxel_labels

from rllock.core import compiled_checkers as checkers
from rllock.core import compiled_sampler as sampler
from rllock.core import reference_checkers as ref
from rllock.core.env import apply_chunk, candidates, initial_state, make_task, sample_accepted


@pytest.mark.parametrize(
    "shape,k,removal,episodes",
    [
        ("cube4", 7, "straight", 6),
        ("cube4", 9, "path", 5),
        ("cube5", 13, "straight", 3),
        ("box:4x3x3", 6, "path", 6),
        ("ring", 15, "straight", 2),
    ],
)
def test_every_check_agrees_with_the_reference(shape, k, removal, episodes):
    """Each of the three checks, on thousands of (state, raw chunk) pairs from random valid states."""
    task = make_task(shape, k, removal)
    topo = task.topology
    rng = np.random.default_rng(k)
    compared, accepted = 0, 0
    for state in random_valid_states(task, rng, episodes):
        chunks = raw_chunks(task, state, rng, 25)
        if len(chunks) == 0:
            continue
        got = checkers.check_chunks(
            topo.arrays,
            state.labels,
            state.placed + 1,
            chunks,
            removal == "path",
        )
        for chunk, bits in zip(chunks, got):
            parts, rest = parts_after(task, state, chunk)
            expected = reference_bits(parts, rest, removal)
            assert bits == expected, (shape, k, state.placed + 1, chunk.tolist())
            compared += 1
            accepted += expected == checkers.ALL_CHECKS
    assert compared >= 300 and 0 < accepted < compared


@pytest.mark.parametrize("removal", ["straight", "path"])
def test_early_exit_sampler_keeps_exactly_the_chunks_full_checks_accept(removal):
    """sample_and_check (early exits) and sample_raw + check_chunks (every check) draw the same random
    stream for the same seed, so they must keep exactly the same chunks, rejections included."""
    task = make_task("cube5", 13, removal)
    topo = task.topology
    rng = np.random.default_rng(4)
    kept_total = 0
    for state in random_valid_states(task, rng, 2):
        seed = int(rng.integers(1 << 30))
        raw = sampler.sample_raw(topo.arrays, state.labels, state.placed + 1, task.piece_size, 300, seed)
        bits = checkers.check_chunks(
            topo.arrays,
            state.labels,
            state.placed + 1,
            raw,
            removal == "path",
        )
        kept = sample_accepted(task, state, seed=seed, num_samples=300)
        np.testing.assert_array_equal(kept, raw[bits == checkers.ALL_CHECKS])
        kept_total += len(kept)
    assert kept_total > 0


def test_accepted_chunks_are_exactly_those_the_reference_accepts():
    task = make_task("cube5", 13)
    rng = np.random.default_rng(3)
    for state in random_valid_states(task, rng, 2):
        for chunk in sample_accepted(task, state, seed=int(rng.integers(1 << 30)), num_samples=256):
            parts, rest = parts_after(task, state, chunk)
            assert len(set(chunk.tolist())) == task.piece_size
            assert ref.is_connected(parts[-1])
            assert reference_bits(parts, rest, "straight") == checkers.ALL_CHECKS


def test_sampler_distribution_matches_the_reference_sampler():
    """On a state with few possible chunks, the fast and the reference sampler draw every chunk with
    the same frequency (two-sample chi-square over the chunk histogram)."""
    task = make_task("box:3x3x2", 6)  # n = 3
    state = apply_chunk(initial_state(task), np.array([0, 1, 2], dtype=np.int32))
    labels = voxel_labels(task, state)
    rng = np.random.default_rng(0)
    draws = 6000

    def histogram(chunks) -> dict[tuple[int, ...], int]:
        counts: dict[tuple[int, ...], int] = {}
        for chunk in chunks:
            key = tuple(sorted(int(v) for v in chunk))
            counts[key] = counts.get(key, 0) + 1
        return counts

    reference = histogram(
        [task.topology.index[v] for v in ref.sample_chunk(labels, 2, 3, rng)] for _ in range(draws)
    )
    topo = task.topology
    compiled = histogram(sampler.sample_raw(topo.arrays, state.labels, 2, 3, draws, 12345))
    assert set(compiled) == set(reference) and len(reference) > 10
    a = np.array([compiled[k] for k in reference], dtype=float)
    b = np.array([reference[k] for k in reference], dtype=float)
    chi2 = (((a - b) ** 2) / (a + b)).sum()
    # Under the null, chi2 ~ chi-square with len-1 degrees of freedom; this bound is its 99.9% quantile
    # for the sizes here, by a wide margin.
    assert chi2 < 2 * len(reference) + 10


def test_same_seed_same_candidates():
    task = make_task("cube4", 8)
    state = initial_state(task)
    a = candidates(task, state, seed=7, num_samples=256, max_candidates=16)
    b = candidates(task, state, seed=7, num_samples=256, max_candidates=16)
    c = candidates(task, state, seed=8, num_samples=256, max_candidates=16)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert len(np.unique(a, axis=0)) == len(a)


@pytest.mark.parametrize("k, n, high", [(0, 5, 9), (1, 5, 9), (7, 1, 3), (300, 4, 6), (512, 15, 800)])
def test_distinct_rows_are_numpys_unique_of_the_sorted_rows(k, n, high):
    """Against the reference `np.unique(np.sort(., axis=1), axis=0)`, on rows drawn from a pool a third
    as large, each in an order of its own (equal as sets, unequal as rows), of voxel numbers below
    `high` (few make rows that share long prefixes)."""
    rng = np.random.default_rng(k + n)
    pool = rng.integers(0, high, (k // 3 + 1, n)).astype(np.int32)
    chunks = rng.permuted(pool[rng.integers(0, len(pool), k)], axis=1)
    got = sampler.distinct_rows(chunks)
    assert got.dtype == chunks.dtype
    np.testing.assert_array_equal(got, np.unique(np.sort(chunks, axis=1), axis=0).reshape(-1, n))
    if k > 1:
        assert len(got) < k


def test_first_voxel_of_a_piece_touches_the_previous_piece():
    task = make_task("cube5", 13)
    rng = np.random.default_rng(5)
    state = next(s for s in random_valid_states(task, rng, 1) if s.placed == 3)
    labels = voxel_labels(task, state)
    for _ in range(200):
        chunk = ref.sample_chunk(labels, 4, task.piece_size, rng)
        assert any(labels.get(ref.shift(chunk[0], d)) == 3 for d in ref.DIRECTIONS)


def test_batched_candidates_equal_one_call_per_node():
    """One compiled call for many nodes (threads over nodes) gives each node exactly what a call of its
    own gives with the same seed."""
    from rllock.core.env import candidates_many

    task = make_task("cube5", 13)
    states = list(random_valid_states(task, np.random.default_rng(7), 2))[:9]
    seeds = np.arange(100, 100 + len(states))
    batched, drawn = candidates_many(task, states, seeds, num_samples=512, max_candidates=16)
    for state, seed, got in zip(states, seeds, batched):
        np.testing.assert_array_equal(
            got, candidates(task, state, seed=int(seed), num_samples=512, max_candidates=16)
        )
    assert drawn > 0 and any(len(b) == 16 for b in batched)


def test_early_stopping_draws_candidates_like_the_full_sample():
    """Stopping at M_c distinct accepted chunks must give the same candidate sets, in distribution, as
    drawing M_c distinct chunks in a random order from the accepted chunks of all M_s samples (the
    reference below, with no early stop). Two-sample chi-square over the sets' histogram."""
    task = make_task("box:3x2x1", 2)  # n = 3: a handful of chunks, drawn with unequal frequencies
    state = initial_state(task)
    m_s, m_c, trials = 8, 2, 3000
    rng = np.random.default_rng(0)

    def reference(seed: int) -> tuple:
        accepted = sample_accepted(task, state, seed=seed, num_samples=m_s)
        keys = []
        for chunk in accepted[rng.permutation(len(accepted))]:
            key = tuple(sorted(int(v) for v in chunk))
            if key not in keys:
                keys.append(key)
        return tuple(sorted(keys[:m_c]))

    def early(seed: int) -> tuple:
        got = candidates(task, state, seed=seed, num_samples=m_s, max_candidates=m_c)
        return tuple(sorted(tuple(int(v) for v in c) for c in got))

    def histogram(draw, offset: int) -> dict:
        counts: dict = {}
        for t in range(trials):
            key = draw(offset + t)
            counts[key] = counts.get(key, 0) + 1
        return counts

    a, b = histogram(early, 0), histogram(reference, 10**6)
    keys = [
        k for k in set(a) | set(b) if a.get(k, 0) + b.get(k, 0) >= 10
    ]  # pooled: rare sets tested together
    assert len(keys) > 5
    x = np.array([a.get(k, 0) for k in keys] + [trials - sum(a.get(k, 0) for k in keys)], float)
    y = np.array([b.get(k, 0) for k in keys] + [trials - sum(b.get(k, 0) for k in keys)], float)
    mask = x + y > 0
    chi2 = (((x - y) ** 2)[mask] / (x + y)[mask]).sum()
    dof = mask.sum() - 1
    assert chi2 < dof + 4 * np.sqrt(2 * dof) + 10  # far beyond the 99.9% quantile under the null


@pytest.mark.parametrize("removal", ["straight", "path"])
def test_every_check_agrees_with_the_reference_with_hundreds_of_pieces(removal):
    """The sparse contact graph, the swept rays and the incremental tests at the scale where they matter:
    states with 50 to 190 of 200 pieces placed on a 1,440-voxel box (prefixes of one search's path),
    raw chunks from the reference sampler and accepted ones from the compiled sampler."""
    from rllock.core.env import State
    from rllock.search.restarts import reach_depth

    task = make_task("box:12x12x10", 200, removal)
    deep = reach_depth(task, 190, seed=1, time_limit=60)
    assert deep is not None
    rng = np.random.default_rng(0)
    compared, accepted = 0, 0
    for depth in (50, 100, 150, 190):
        state = State(np.where(deep.labels <= depth, deep.labels, 0).astype(np.int16), depth)
        mine = sample_accepted(task, state, seed=depth, num_samples=256, closed_share=0.5)[:10]
        chunks = np.concatenate([raw_chunks(task, state, rng, 20), mine])
        got = checkers.check_chunks(task.topology.arrays, state.labels, depth + 1, chunks, removal == "path")
        for chunk, bits in zip(chunks, got):
            parts, rest = parts_after(task, state, chunk)
            assert bits == reference_bits(parts, rest, removal), (depth, chunk.tolist())
            compared += 1
            accepted += bits == checkers.ALL_CHECKS
    assert compared >= 80 and 20 < accepted < compared
