"""The compiled chunk sampler and the candidates of search nodes (numba).

A raw chunk for piece i grows from a seed voxel of R_(i-1) that touches P_(i-1), one uniformly drawn
frontier voxel at a time, to n voxels; `compiled_checkers` accepts or rejects it.

The closed proposal (`_sample_closed_chunk`, used by the search solver through `sample_and_check_mixed`)
builds straight removability in, for big pieces on big shapes, where frontier chunks almost never slide
out: it draws a direction d, and every voxel it adds brings the R voxels beyond it along d, so the chunk
slides out along d by construction. The checkers still decide on every chunk. MCTS, the shipped networks
and everything else use frontier growth alone; with a closed share of 0 the random stream is unchanged.

A search node's candidates (`node_candidates`, and `candidates_many` for a whole batch of nodes, one
thread per node with `prange`) are the first M_c distinct accepted chunks in sampling order, drawn from
at most M_s raw samples: sampling stops as soon as M_c distinct ones are found. Since raw samples are
independent and identically distributed, that is the same distribution as taking the accepted chunks
of all M_s samples in a random order and keeping the first M_c distinct ones (a chunk the sampler
draws more often is more likely to be a candidate); tests/test_compiled.py checks it statistically.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from rllock.core import numba_cache  # noqa: F401  (before any @njit: it picks the cache folder)
from rllock.core.compiled_checkers import ALL_CHECKS, check_chunk, prepare_node, scratch_arrays


@njit(cache=True, nogil=True)
def _rng(seed):
    """A xorshift64* generator's state (uint64[1]), from any int seed through splitmix64. It is 7x
    cheaper per draw than numba's np.random, and each caller holds its own, so streams do not depend
    on threads."""
    z = np.uint64(seed) + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    z ^= z >> np.uint64(31)
    state = np.empty(1, np.uint64)
    state[0] = z if z != np.uint64(0) else np.uint64(1)
    return state


@njit(cache=True, nogil=True)
def _below(state, bound):
    """A draw from 0..bound-1 (bound < 2**31): the high 32 bits scaled by multiply-shift (Lemire),
    whose bias, at most bound / 2**32, is far below anything a sample of chunks can show."""
    x = state[0]
    x ^= x >> np.uint64(12)
    x ^= x << np.uint64(25)
    x ^= x >> np.uint64(27)
    state[0] = x
    r = (x * np.uint64(0x2545F4914F6CDD1D)) >> np.uint64(32)
    return np.int64((r * np.uint64(bound)) >> np.uint64(32))


@njit(cache=True, nogil=True)
def _degree(r_nbr, v):
    """How many R neighbours R voxel v has."""
    d = 0
    while d < 6 and r_nbr[v, d] >= 0:
        d += 1
    return d


@njit(cache=True, nogil=True)
def _frontier_pick(rng, r_nbr, front, nf, thin):
    """The index in front[:nf] of the next voxel to grow into: the thinnest (fewest R neighbours) of
    1 + thin uniform draws; with thin 0 (or one voxel), exactly one draw."""
    pick = _below(rng, nf)
    if thin > 0 and nf > 1:
        best = _degree(r_nbr, front[pick])
        for _ in range(thin):
            other = _below(rng, nf)
            deg = _degree(r_nbr, front[other])
            if deg < best:
                pick, best = other, deg
    return pick


@njit(cache=True, nogil=True)
def _touching_placed(nbr, labels):
    """The R voxels (label 0) that touch a placed piece."""
    out = np.empty(labels.shape[0], np.int32)
    k = 0
    for v in range(labels.shape[0]):
        if labels[v] != 0:
            continue
        for t in range(6):
            u = nbr[v, t]
            if u >= 0 and labels[u] > 0:
                out[k] = v
                k += 1
                break
    return out[:k]


@njit(cache=True)
def _sample_chunk(rng, seeds, r_nbr, n, chunk, in_chunk, front, front_mark, stamp, thin):
    """Grow one raw chunk into `chunk` and stamp it in `in_chunk`; False if it cannot reach n voxels.
    r_nbr lists each R voxel's R neighbours (-1 after the last); `front_mark` holds `stamp` for the
    chunk's voxels and its frontier, so one load tells whether a neighbour is new. With `thin` > 0, a
    frontier voxel is the thinnest of 1 + thin uniform draws (as the closed proposal's, THIN); with 0
    the random stream is that of uniform growth."""
    v = seeds[_below(rng, seeds.shape[0])]
    chunk[0] = v
    in_chunk[v] = stamp
    front_mark[v] = stamp
    nf = 0
    for j in range(n):
        if j > 0:
            if nf == 0:
                return False
            pick = _frontier_pick(rng, r_nbr, front, nf, thin)
            v = front[pick]
            nf -= 1
            front[pick] = front[nf]
            chunk[j] = v
            in_chunk[v] = stamp
        for t in range(6):
            u = r_nbr[v, t]
            if u < 0:
                break
            if front_mark[u] != stamp:
                front_mark[u] = stamp
                front[nf] = u
                nf += 1
    return True


# The closed proposal draws a frontier voxel as the thinner (fewer neighbours in R) of 1 + THIN uniform
# draws: peeling thin parts first leaves a compact remaining volume, which deep searches need (measured
# on desia-bunny K=60 and desia-dog K=40, 4 seeds each: 3 of 8 found in 20 s with it, 0 of 8 without).
THIN = 1


@njit(cache=True, nogil=True)
def _closed_run(u, d, n_left, nbr, ray, ray_r, part_of, r_node, in_chunk, stamp, run):
    """The voxels that adding R voxel u to a chunk closed along direction d brings with it: u and the
    R voxels beyond it along d up to the chunk (or the end of R), written to `run`. Returns their
    count, or -1 if there are more than `n_left` or they are not contiguous (an R voxel beyond a gap
    would not be connected to the chunk)."""
    m = 0
    w = u
    while True:
        if m >= n_left:
            return -1
        run[m] = w
        m += 1
        x = nbr[w, d]
        if x >= 0 and part_of[x] == r_node:
            if in_chunk[x] == stamp:
                return m
            w = x
            continue
        if ray_r[w, d] == 0:
            return m
        y = ray[w, d]
        while part_of[y] != r_node:
            y = ray[y, d]
        return m if in_chunk[y] == stamp else -1


@njit(cache=True, nogil=True)
def _sample_closed_chunk(rng, seeds, topo, node, r_node, n, chunk, in_chunk, front, front_mark, run, stamp):
    """Grow one raw chunk closed along a random direction d within R: with every voxel, all R voxels
    beyond it along d, so that it slides out along d. From a seed voxel (as `_sample_chunk`), each step
    adds a uniformly drawn frontier voxel with its run along d (`_closed_run`); a frontier voxel whose
    run does not fit is dropped and may come back when a later voxel touches it. Returns d, or -1 if
    the chunk cannot reach exactly n voxels this way."""
    nbr, ray = topo[0], topo[1]
    part_of, ray_r, r_nbr = node[0], node[2], node[5]
    v = seeds[_below(rng, seeds.shape[0])]
    d = _below(rng, 6)
    size = 0
    nf = 0
    m = _closed_run(v, d, n, nbr, ray, ray_r, part_of, r_node, in_chunk, stamp, run)
    if m < 0:
        return -1
    while True:
        for i in range(m):
            w = run[i]
            chunk[size] = w
            size += 1
            in_chunk[w] = stamp
            front_mark[w] = stamp
        for i in range(m):
            w = run[i]
            for t in range(6):
                u = r_nbr[w, t]
                if u < 0:
                    break
                if front_mark[u] != stamp:
                    front_mark[u] = stamp
                    front[nf] = u
                    nf += 1
        if size == n:
            return d
        m = -1
        while m < 0:
            if nf == 0:
                return -1
            pick = _frontier_pick(rng, r_nbr, front, nf, THIN)
            u = front[pick]
            nf -= 1
            front[pick] = front[nf]
            if in_chunk[u] == stamp:
                continue
            m = _closed_run(u, d, n - size, nbr, ray, ray_r, part_of, r_node, in_chunk, stamp, run)
            if m < 0:
                front_mark[u] = 0


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
    proposal (`_sample_closed_chunk`) instead of frontier growth, frontier voxels drawn as the thinnest
    of 1 + `thin` (`_sample_chunk`), and with `wide_seeds`, chunks started at any R voxel that touches a
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
    rng = _rng(seed)
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
        if _sample_chunk(rng, seeds, r_nbr, n, out[k], in_chunk, front, front_mark, s + 1, 0):
            k += 1
    return out[:k]


@njit(cache=True)
def sample_raw_closed(topo, labels, piece, n, num_samples, seed):
    """Unchecked raw chunks of the closed proposal (those that grew to n voxels) and the direction each
    is closed along: (int32[k, n], int64[k]). For testing the proposal."""
    rng = _rng(seed)
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
        d = _sample_closed_chunk(
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
    rng = _rng(seed)
    nbr, ray, _, n_lines, _, index = topo
    node = prepare_node(nbr, ray, labels, piece)
    seeds, r_nbr = node[1], node[5]
    if wide_seeds and piece > 1:
        seeds = _touching_placed(nbr, labels)
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
        if share > 0 and (share >= 1 << 30 or _below(rng, 1 << 30) < share):
            grown = (
                _sample_closed_chunk(
                    rng, seeds, topo, node, piece, n, chunk, in_chunk, front, front_mark, run, s
                )
                >= 0
            )
        else:
            grown = _sample_chunk(rng, seeds, r_nbr, n, chunk, in_chunk, front, front_mark, s, thin)
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
