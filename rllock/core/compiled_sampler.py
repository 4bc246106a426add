"""The compiled chunk sampler and the candidates of search nodes (numba).

A raw chunk for piece i grows from a seed voxel of R_(i-1) that touches P_(i-1), one uniformly drawn
frontier voxel at a time, to n voxels; `compiled_checkers` accepts or rejects it.

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


@njit(cache=True)
def _sample_chunk(rng, seeds, r_nbr, n, chunk, in_chunk, front, front_mark, stamp):
    """Grow one raw chunk into `chunk` and stamp it in `in_chunk`; False if it cannot reach n voxels.
    r_nbr lists each R voxel's R neighbours (-1 after the last); `front_mark` holds `stamp` for the
    chunk's voxels and its frontier, so one load tells whether a neighbour is new."""
    v = seeds[_below(rng, seeds.shape[0])]
    chunk[0] = v
    in_chunk[v] = stamp
    front_mark[v] = stamp
    nf = 0
    for j in range(n):
        if j > 0:
            if nf == 0:
                return False
            pick = _below(rng, nf)
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


@njit(cache=True)
def sample_and_check(topo, labels, piece, n, num_samples, removal_path, seed):
    """Sample `num_samples` raw chunks for piece `piece` and keep those the checkers accept.
    topo = (nbr, ray, line, n_lines, coords, index), as `Topology.arrays`.

    Returns (accepted int32[k, n], k). Chunks that fail to grow to n voxels count as rejected.
    """
    accepted = np.empty((num_samples, n), np.int32)
    k, _ = _sample_into(topo, labels, piece, n, num_samples, num_samples, False, removal_path, seed, accepted)
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
        if _sample_chunk(rng, seeds, r_nbr, n, out[k], in_chunk, front, front_mark, s + 1):
            k += 1
    return out[:k]


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
    return _sample_into(topo, labels, piece, n, num_samples, max_candidates, True, removal_path, seed, out)


@njit(cache=True, nogil=True)
def _sample_into(topo, labels, piece, n, num_samples, keep, distinct, removal_path, seed, out):
    """Draw raw chunks for piece `piece` (at most `num_samples`) and write the accepted ones into `out`
    until `keep` are kept; with `distinct`, as sorted voxel numbers without repeats. Returns (kept, drawn)."""
    rng = _rng(seed)
    nbr, ray, _, n_lines, _, index = topo
    node = prepare_node(nbr, ray, labels, piece)
    seeds, r_nbr = node[1], node[5]
    if seeds.shape[0] == 0:
        return 0, 0
    n_vox = labels.shape[0]
    scratch = scratch_arrays(n_vox, n_lines, piece + 1, index.shape)
    in_chunk = scratch[0]
    front_mark = np.zeros(n_vox, np.int64)
    front = np.empty(n_vox, np.int32)
    chunk = np.empty(n, np.int32)
    k = 0
    s = 0
    while s < num_samples and k < keep:
        s += 1
        if not _sample_chunk(rng, seeds, r_nbr, n, chunk, in_chunk, front, front_mark, s):
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
