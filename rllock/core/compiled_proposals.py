"""How the compiled sampler grows raw chunks (numba): its random numbers and its two proposals.

A raw chunk for piece i grows from a seed voxel of R_(i-1) that touches P_(i-1), one uniformly drawn
frontier voxel at a time, to n voxels (`sample_chunk`); `compiled_checkers` accepts or rejects it, and
`compiled_sampler` puts the two together.

The closed proposal (`sample_closed_chunk`, used by the search solver through
`compiled_sampler.sample_and_check_mixed`) builds straight removability in, for big pieces on big
shapes, where frontier chunks almost never slide out: it draws a direction d, and every voxel it adds
brings the R voxels beyond it along d, so the chunk slides out along d by construction. The checkers
still decide on every chunk. MCTS, the shipped networks and everything else use frontier growth alone;
with a closed share of 0 the random stream is unchanged.

Each caller holds a generator of its own (`seeded_rng`, drawn from with `below`), so that what a search
node samples depends on its seed alone, not on the threads around it.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from rllock.core import numba_cache  # noqa: F401  (before any @njit: it picks the cache folder)


@njit(cache=True, nogil=True)
def seeded_rng(seed):
    """A xorshift64* generator's state (uint64[1]), from any int seed through splitmix64. It is much
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
def below(state, bound):
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
    pick = below(rng, nf)
    if thin > 0 and nf > 1:
        best = _degree(r_nbr, front[pick])
        for _ in range(thin):
            other = below(rng, nf)
            deg = _degree(r_nbr, front[other])
            if deg < best:
                pick, best = other, deg
    return pick


@njit(cache=True, nogil=True)
def touching_placed(nbr, labels):
    """The R voxels (label 0) that touch a placed piece: the seeds of chunks that may start beside any
    placed piece, not only the previous one (`compiled_sampler.sample_and_check_mixed`'s wide seeds)."""
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
def sample_chunk(rng, seeds, r_nbr, n, chunk, in_chunk, front, front_mark, stamp, thin):
    """Grow one raw chunk into `chunk` and stamp it in `in_chunk`; False if it cannot reach n voxels.
    r_nbr lists each R voxel's R neighbours (-1 after the last); `front_mark` holds `stamp` for the
    chunk's voxels and its frontier, so one load tells whether a neighbour is new. With `thin` > 0, a
    frontier voxel is the thinnest of 1 + thin uniform draws (as the closed proposal's, THIN); with 0
    the random stream is that of uniform growth."""
    v = seeds[below(rng, seeds.shape[0])]
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
# draws: peeling thin parts first leaves a compact remaining volume, which deep searches on large meshes
# need to find assemblies at all.
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
def sample_closed_chunk(rng, seeds, topo, node, r_node, n, chunk, in_chunk, front, front_mark, run, stamp):
    """Grow one raw chunk closed along a random direction d within R: with every voxel, all R voxels
    beyond it along d, so that it slides out along d. From a seed voxel (as `sample_chunk`), each step
    adds a uniformly drawn frontier voxel with its run along d (`_closed_run`); a frontier voxel whose
    run does not fit is dropped and may come back when a later voxel touches it. Returns d, or -1 if
    the chunk cannot reach exactly n voxels this way."""
    nbr, ray = topo[0], topo[1]
    part_of, ray_r, r_nbr = node[0], node[2], node[5]
    v = seeds[below(rng, seeds.shape[0])]
    d = below(rng, 6)
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
