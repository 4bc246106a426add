"""The compiled chunk sampler and the candidates of search nodes (numba): raw chunks drawn by
`compiled_proposals` and kept when `compiled_checkers` accepts them.

A search node's candidates (`node_candidates`, and `candidates_many` for a whole batch of nodes, one
thread per node with `prange`) are the first M_c distinct accepted chunks in sampling order, drawn from
at most M_s raw samples: sampling stops as soon as M_c distinct ones are found. Since raw samples are
independent and identically distributed, that is the same distribution as taking the accepted chunks
of all M_s samples in a random order and keeping the first M_c distinct ones (a chunk the sampler
draws more often is more likely to be a candidate); tests/test_compiled.py checks it statistically.

The unchecked raw chunks of either proposal (`sample_raw`, `sample_raw_closed`) are here too, beside
the other entry points, for testing the proposals against the checked streams.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from rllock.core import numba_cache  # noqa: F401  (before any @njit: it picks the cache folder)
from rllock.core.compiled_checkers import ALL_CHECKS, check_chunk, prepare_node, scratch_arrays
from rllock.core.compiled_proposals import (
    below,
    sample_chunk,
    sample_closed_chunk,
    seeded_rng,
    touching_placed,
)


@njit(cache=True)
def sample_and_check(topo, labels, piece, n, num_samples, removal_path, seed):
    """Sample `num_samples` raw chunks for piece `piece` and keep those the checkers accept.
    topo = (nbr, ray, line, n_lines, coords, index), as `Topology.arrays`.

    Returns (accepted int32[k, n], k). Chunks that fail to grow to n voxels count as rejected.
    """
    accepted = np.empty((num_samples, n), np.int32)
    k, _ = _sample_into(
        topo, labels, piece, n, num_samples, num_samples, False, removal_path, seed, 0.0, accepted
    )
    return accepted[:k], k


@njit(cache=True, nogil=True)
def sample_and_check_mixed(
    topo, labels, piece, n, num_samples, removal_path, seed, closed_share, thin=0, wide_seeds=False
):
    """`sample_and_check` with a share `closed_share` (0..1) of the raw chunks drawn by the closed
    proposal (`sample_closed_chunk`) instead of frontier growth, frontier voxels drawn as the thinnest
    of 1 + `thin` (`sample_chunk`), and with `wide_seeds`, chunks started at any R voxel that touches a
    placed piece, not only the previous one; the defaults are exactly `sample_and_check`. Every chunk
    still passes all the checks. Returns (accepted int32[k, n], k)."""
    accepted = np.empty((num_samples, n), np.int32)
    k, _ = _sample_into(
        topo,
        labels,
        piece,
        n,
        num_samples,
        num_samples,
        False,
        removal_path,
        seed,
        closed_share,
        accepted,
        thin,
        wide_seeds,
    )
    return accepted[:k], k


@njit(cache=True)
def sample_raw(topo, labels, piece, n, num_samples, seed):
    """Unchecked raw chunks (those that grew to n voxels): int32[k, n]. For testing the sampler."""
    rng = seeded_rng(seed)
    nbr, ray = topo[0], topo[1]
    node = prepare_node(nbr, ray, labels, piece)
    seeds, r_nbr = node[1], node[5]
    n_vox = labels.shape[0]
    out = np.empty((num_samples, n), np.int32)
    if seeds.shape[0] == 0:
        return out[:0]
    in_chunk = np.zeros(n_vox, np.int64)
    front_mark = np.zeros(n_vox, np.int64)
    front = np.empty(n_vox, np.int32)
    k = 0
    for s in range(num_samples):
        if sample_chunk(rng, seeds, r_nbr, n, out[k], in_chunk, front, front_mark, s + 1, 0):
            k += 1
    return out[:k]


@njit(cache=True)
def sample_raw_closed(topo, labels, piece, n, num_samples, seed):
    """Unchecked raw chunks of the closed proposal (those that grew to n voxels) and the direction each
    is closed along: (int32[k, n], int64[k]). For testing the proposal."""
    rng = seeded_rng(seed)
    node = prepare_node(topo[0], topo[1], labels, piece)
    seeds = node[1]
    n_vox = labels.shape[0]
    out = np.empty((num_samples, n), np.int32)
    dirs = np.empty(num_samples, np.int64)
    if seeds.shape[0] == 0:
        return out[:0], dirs[:0]
    in_chunk = np.zeros(n_vox, np.int64)
    front_mark = np.zeros(n_vox, np.int64)
    front = np.empty(n_vox, np.int32)
    run = np.empty(n, np.int32)
    k = 0
    for s in range(num_samples):
        d = sample_closed_chunk(
            rng, seeds, topo, node, piece, n, out[k], in_chunk, front, front_mark, run, s + 1
        )
        if d >= 0:
            dirs[k] = d
            k += 1
    return out[:k], dirs[:k]


@njit(cache=True, nogil=True)
def _insertion_sort(values, n):
    for i in range(1, n):
        x = values[i]
        j = i - 1
        while j >= 0 and values[j] > x:
            values[j + 1] = values[j]
            j -= 1
        values[j + 1] = x


@njit(cache=True, nogil=True)
def _seen(out, k, chunk, n):
    for c in range(k):
        same = True
        for j in range(n):
            if out[c, j] != chunk[j]:
                same = False
                break
        if same:
            return True
    return False


@njit(cache=True, nogil=True)
def node_candidates(topo, labels, piece, n, num_samples, max_candidates, removal_path, seed, out):
    """A node's candidate actions into `out` [>= max_candidates, n]: the first `max_candidates` distinct
    accepted chunks (sorted voxel numbers) among at most `num_samples` raw samples, in sampling order.
    Returns (candidates found, raw samples drawn)."""
    return _sample_into(
        topo, labels, piece, n, num_samples, max_candidates, True, removal_path, seed, 0.0, out
    )


@njit(cache=True, nogil=True)
def _sample_into(
    topo,
    labels,
    piece,
    n,
    num_samples,
    keep,
    distinct,
    removal_path,
    seed,
    closed_share,
    out,
    thin=0,
    wide_seeds=False,
):
    """Draw raw chunks for piece `piece` (at most `num_samples`) and write the accepted ones into `out`
    until `keep` are kept; with `distinct`, as sorted voxel numbers without repeats. A share
    `closed_share` of the chunks comes from the closed proposal; with 0 (and `thin` 0, `wide_seeds`
    off: `sample_and_check_mixed`) the random stream is that of frontier growth alone. Returns (kept,
    drawn)."""
    rng = seeded_rng(seed)
    nbr, ray, _, n_lines, _, index = topo
    node = prepare_node(nbr, ray, labels, piece)
    seeds, r_nbr = node[1], node[5]
    if wide_seeds and piece > 1:
        seeds = touching_placed(nbr, labels)
    if seeds.shape[0] == 0:
        return 0, 0
    n_vox = labels.shape[0]
    scratch = scratch_arrays(n_vox, n_lines, piece + 1, index.shape, removal_path)
    in_chunk = scratch[0]
    front_mark = np.zeros(n_vox, np.int64)
    front = np.empty(n_vox, np.int32)
    chunk = np.empty(n, np.int32)
    run = np.empty(n, np.int32)
    share = np.int64(closed_share * 2.0**30)
    k = 0
    s = 0
    while s < num_samples and k < keep:
        s += 1
        if share > 0 and (share >= 1 << 30 or below(rng, 1 << 30) < share):
            grown = (
                sample_closed_chunk(
                    rng, seeds, topo, node, piece, n, chunk, in_chunk, front, front_mark, run, s
                )
                >= 0
            )
        else:
            grown = sample_chunk(rng, seeds, r_nbr, n, chunk, in_chunk, front, front_mark, s, thin)
        if not grown:
            continue
        if check_chunk(chunk, n, piece, topo, node, removal_path, False, scratch, s) != ALL_CHECKS:
            continue
        if distinct:
            _insertion_sort(chunk, n)
            if _seen(out, k, chunk, n):
                continue
        out[k, :] = chunk
        k += 1
    return k, s


@njit(cache=True, nogil=True)
def _candidates_row(
    topo, labels, pieces, seeds, n, num_samples, max_candidates, removal_path, out, found, drawn, b
):
    found[b], drawn[b] = node_candidates(
        topo, labels[b], pieces[b], n, num_samples, max_candidates, removal_path, seeds[b], out[b]
    )


@njit(cache=True, nogil=True, parallel=True)
def candidates_many(topo, labels, pieces, seeds, n, num_samples, max_candidates, removal_path):
    """`node_candidates` for B nodes at once, one thread per node. topo = (nbr, ray, line, n_lines,
    coords, index); labels int16[B, N], pieces and seeds int64[B] -> (candidates int32[B, max_candidates,
    n], counts int32[B], raw samples drawn int64[B]). Each node seeds a generator of its own, so the
    result does not depend on the thread count."""
    out = np.zeros((labels.shape[0], max_candidates, n), np.int32)
    found = np.zeros(labels.shape[0], np.int32)
    drawn = np.zeros(labels.shape[0], np.int64)
    for b in prange(labels.shape[0]):
        _candidates_row(
            topo, labels, pieces, seeds, n, num_samples, max_candidates, removal_path, out, found, drawn, b
        )
    return out, found, drawn


@njit(cache=True, nogil=True)
def candidates_serial(topo, labels, pieces, seeds, n, num_samples, max_candidates, removal_path):
    """`candidates_many` on the calling thread alone: for callers that run several lockstep groups in
    threads of their own (numba's default threading layer aborts on concurrent parallel launches)."""
    out = np.zeros((labels.shape[0], max_candidates, n), np.int32)
    found = np.zeros(labels.shape[0], np.int32)
    drawn = np.zeros(labels.shape[0], np.int64)
    for b in range(labels.shape[0]):
        _candidates_row(
            topo, labels, pieces, seeds, n, num_samples, max_candidates, removal_path, out, found, drawn, b
        )
    return out, found, drawn


@njit(cache=True, nogil=True)
def remainder_growth(nbr, labels, chunks, outside):
    """int64[k]: for each chunk (a row of voxel numbers of R, labels 0), how much the remaining volume's
    surface grows when the chunk leaves it: the faces the chunk shares with the rest of R (its cut), less
    `outside` times its faces to placed pieces and to the outside of the shape, which R loses with it.
    `outside` = 1 is the surface's change; 0, the cut alone. A small growth leaves a compact remainder."""
    mark = np.zeros(labels.shape[0], np.int64)
    out = np.zeros(chunks.shape[0], np.int64)
    for c in range(chunks.shape[0]):
        for j in range(chunks.shape[1]):
            mark[chunks[c, j]] = c + 1
        growth = 0
        for j in range(chunks.shape[1]):
            for t in range(6):
                u = nbr[chunks[c, j], t]
                if u < 0 or labels[u] != 0:
                    growth -= outside
                elif mark[u] != c + 1:
                    growth += 1
        out[c] = growth
    return out


@njit(cache=True, nogil=True)
def _row_less(rows, a, b):
    """Whether row a of `rows` comes before row b in lexicographic order."""
    for j in range(rows.shape[1]):
        if rows[a, j] != rows[b, j]:
            return rows[a, j] < rows[b, j]
    return False


@njit(cache=True, nogil=True)
def distinct_rows(chunks):
    """The distinct chunks of `chunks` [k, n] as sorted voxel numbers, in lexicographic order:
    `np.unique(np.sort(chunks, axis=1), axis=0)` without the GIL, so that a node's children sampled on
    threads (`solver.SamplingPool`) do not wait on each other's bookkeeping. A bottom-up merge sort of
    the row indices: k is a node's accepted samples, a few hundred at most."""
    k, n = chunks.shape
    rows = chunks.copy()
    for r in range(k):
        _insertion_sort(rows[r], n)
    order = np.arange(k)
    spare = np.empty(k, np.int64)
    width = 1
    while width < k:
        for lo in range(0, k, 2 * width):
            mid, hi = min(lo + width, k), min(lo + 2 * width, k)
            i, j, o = lo, mid, lo
            while i < mid and j < hi:
                if _row_less(rows, order[j], order[i]):
                    spare[o] = order[j]
                    j += 1
                else:
                    spare[o] = order[i]
                    i += 1
                o += 1
            while i < mid:
                spare[o] = order[i]
                i += 1
                o += 1
            while j < hi:
                spare[o] = order[j]
                j += 1
                o += 1
        order, spare = spare, order
        width *= 2
    out = np.empty((k, n), chunks.dtype)
    m = 0
    for r in range(k):
        row = order[r]
        same = m > 0
        if same:
            for j in range(n):
                if out[m - 1, j] != rows[row, j]:
                    same = False
                    break
        if not same:
            out[m] = rows[row]
            m += 1
    return out[:m]
