"""The interlocking check of the compiled checkers (numba): the contact graph of a search node and
the test on A_i for each chunk.

`compiled_checkers.prepare_node` builds, once per search node, the face contacts along each +axis in
A_(i-1) (`contact_graph`): those of R and of the new piece as counts per node, those between placed
pieces as adjacency lists (sparse, since a piece touches few others and K reaches thousands), and
base_ok: per axis, whether A_(i-1)'s graph is strongly connected, with and without the key
(`base_interlocking`). Per chunk (`interlocking`), the new piece must touch the shape in all 6
directions; the contact counts of A_i are those of A_(i-1) with the chunk's contacts moved from R to
the new piece; where R lost no contact and A_(i-1) was strongly connected on an axis, the new piece's
contacts decide, and otherwise a strong-connectivity test runs on that axis.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from rllock.core import numba_cache  # noqa: F401  (before any @njit: it picks the cache folder)

# Rows of `contact_graph`'s counts: an out row and its in row are one apart, so that a search against the
# edges (direction 1) reads row + 1 where one along them (direction 0) reads row, or row - 1 for an IN.
R_OUT, R_IN, NEW_OUT, NEW_IN = 0, 1, 2, 3


@njit(cache=True)
def contact_graph(nbr, part_of, n_parts):
    """The face contacts of A_(i-1) per axis, sparse, so that work grows with the contacts and not with
    the square of the piece count. Nodes: placed pieces 0..i-2, the new piece i-1, R = i. Returns
    (counts, starts, adj): counts[R_OUT, a, q] counts the contacts R -> q along +a and counts[R_IN, a, q]
    those q -> R (NEW_OUT and NEW_IN the same for the new piece, zero until a chunk's contacts are moved
    in, and the only place of those between it and R); the contacts between placed pieces, which no
    chunk changes, are adjacency lists without repeats: the heads of p's edges along +a are
    adj[starts[0, a, p]:starts[0, a, p + 1]], the tails of the edges into p likewise from starts[1].
    Three arrays, not eight: every array passed to a compiled call is reference-counted, per chunk."""
    r_node = n_parts - 1
    counts = np.zeros((4, 3, n_parts), np.int32)
    out_deg = np.zeros(3 * n_parts + 1, np.int64)
    in_deg = np.zeros(3 * n_parts + 1, np.int64)
    for v in range(part_of.shape[0]):
        p = part_of[v]
        for a in range(3):
            u = nbr[v, 2 * a]
            if u < 0 or part_of[u] == p:
                continue
            q = part_of[u]
            if p == r_node:
                counts[R_OUT, a, q] += 1
            elif q == r_node:
                counts[R_IN, a, p] += 1
            else:
                out_deg[a * n_parts + p + 1] += 1
                in_deg[a * n_parts + q + 1] += 1
    for i in range(3 * n_parts):
        out_deg[i + 1] += out_deg[i]
        in_deg[i + 1] += in_deg[i]
    out_adj = np.empty(out_deg[-1], np.int32)
    in_adj = np.empty(in_deg[-1], np.int32)
    out_fill = out_deg[:-1].copy()
    in_fill = in_deg[:-1].copy()
    for v in range(part_of.shape[0]):
        p = part_of[v]
        if p == r_node:
            continue
        for a in range(3):
            u = nbr[v, 2 * a]
            if u < 0 or part_of[u] == p or part_of[u] == r_node:
                continue
            q = part_of[u]
            out_adj[out_fill[a * n_parts + p]] = q
            out_fill[a * n_parts + p] += 1
            in_adj[in_fill[a * n_parts + q]] = p
            in_fill[a * n_parts + q] += 1
    out_start, out_adj = _unique_rows(out_deg, out_adj, n_parts)
    in_start, in_adj = _unique_rows(in_deg, in_adj, n_parts)
    starts = np.stack((out_start, in_start + out_adj.shape[0]))
    return counts, starts, np.concatenate((out_adj, in_adj))


@njit(cache=True)
def _unique_rows(start, adj, n_parts):
    """Adjacency rows (row r = adj[start[r]:start[r + 1]]) without repeats, as ([3, n_parts + 1] row
    starts, the compacted list): row a * n_parts + p holds axis a, node p."""
    mark = np.full(n_parts, -1, np.int64)
    out = np.empty(adj.shape[0], np.int32)
    rows = np.zeros((3, n_parts + 1), np.int64)
    m = 0
    for r in range(3 * n_parts):
        a, p = r // n_parts, r % n_parts
        rows[a, p] = m
        for i in range(start[r], start[r + 1]):
            q = adj[i]
            if mark[q] != r:
                mark[q] = r
                out[m] = q
                m += 1
        rows[a, p + 1] = m
    return rows, out[:m]


@njit(cache=True, inline="always")
def _visit(q, seen, stack, top):
    """Pushes q if it is new; returns the new stack top."""
    if seen[q]:
        return top
    seen[q] = True
    stack[top] = q
    return top + 1


@njit(cache=True, inline="always")
def _dense_row(row, n_parts, seen, stack, top):
    """Pushes the new nodes q with row[q] > 0 (the contacts of R or of the new piece)."""
    for q in range(n_parts):
        if row[q] > 0:
            top = _visit(q, seen, stack, top)
    return top


@njit(cache=True)
def _strongly_connected(contacts, a, n_parts, skip, absent, seen, stack):
    """Whether the axis-a contact graph on the nodes other than `skip` and `absent` (-1: none) is
    strongly connected: everything reached from one node along the edges and against them."""
    counts, starts, adj = contacts
    r_node, new = n_parts - 1, n_parts - 2
    start = 0
    while start == skip or start == absent:
        start += 1
    size = n_parts - (skip >= 0) - (absent >= 0)
    for direction in range(2):
        seen[:n_parts] = False
        if skip >= 0:
            seen[skip] = True
        if absent >= 0:
            seen[absent] = True
        seen[start] = True
        stack[0] = start
        top = 1
        reached = 1
        while top > 0:
            top -= 1
            p = stack[top]
            before = top
            if p == r_node:
                top = _dense_row(counts[R_OUT + direction, a], n_parts, seen, stack, top)
                # The contacts between R and the new piece are kept as the new piece's only.
                if counts[NEW_IN - direction, a, r_node] > 0:
                    top = _visit(new, seen, stack, top)
            elif p == new:
                top = _dense_row(counts[NEW_OUT + direction, a], n_parts, seen, stack, top)
            else:
                # p -> R is an R in-contact of p, R -> p an out-contact; the same for the new piece.
                for i in range(starts[direction, a, p], starts[direction, a, p + 1]):
                    top = _visit(adj[i], seen, stack, top)
                to_r, to_new = counts[R_IN - direction, a, p], counts[NEW_IN - direction, a, p]
                if to_r > 0:
                    top = _visit(r_node, seen, stack, top)
                if to_new > 0:
                    top = _visit(new, seen, stack, top)
            reached += top - before
            if reached == size:  # everything reached: the nodes still on the stack add nothing
                break
        if reached != size:
            return False
    return True


@njit(cache=True)
def base_interlocking(contacts, n_parts):
    """Per axis, whether A_(i-1)'s graph (without the still empty new node) is strongly connected
    [a, 0], and whether it is without the key [a, 1]."""
    seen = np.zeros(n_parts, np.bool_)
    stack = np.empty(n_parts, np.int32)
    out = np.zeros((3, 2), np.bool_)
    new = n_parts - 2
    for a in range(3):
        out[a, 0] = _strongly_connected(contacts, a, n_parts, -1, new, seen, stack)
        out[a, 1] = _strongly_connected(contacts, a, n_parts, 0, new, seen, stack)
    return out


@njit(cache=True)
def _held_every_way(chunk, n, nbr, in_chunk, stamp):
    """Whether the chunk touches another voxel of the shape in each of the 6 directions. A new piece
    that does not can slide one step that way, so A_i is not interlocking: a cheap first rejection."""
    need = 63
    for j in range(n):
        v = chunk[j]
        for k in range(6):
            u = nbr[v, k]
            if u >= 0 and in_chunk[u] != stamp:
                need &= ~(1 << k)
        if need == 0:
            return True
    return False


@njit(cache=True)
def _move_contacts(chunk, n, nbr, part_of, r_node, in_chunk, contacts, stamp, sign):
    """Moves the chunk's face contacts from R to the new piece in `contacts` (sign 1), or back (-1).
    Returns (whether a contact between R and another node dropped to zero, that is an edge was lost;
    a bitmask of the new piece's contacts with nodes other than the key: bit a for an edge into it
    along +a, bit 3 + a for one out of it)."""
    counts = contacts[0]
    lost = False
    away_from_key = 0
    for j in range(n):
        v = chunk[j]
        for a in range(3):
            u = nbr[v, 2 * a]  # v -> u along +a
            if u >= 0 and in_chunk[u] != stamp:
                q = part_of[u]
                if q != r_node:
                    counts[R_OUT, a, q] -= sign
                    lost |= counts[R_OUT, a, q] == 0
                counts[NEW_OUT, a, q] += sign
                if q != 0:
                    away_from_key |= 1 << (3 + a)
            u = nbr[v, 2 * a + 1]  # u -> v along +a
            if u >= 0 and in_chunk[u] != stamp:
                q = part_of[u]
                if q != r_node:
                    counts[R_IN, a, q] -= sign
                    lost |= counts[R_IN, a, q] == 0
                counts[NEW_IN, a, q] += sign
                if q != 0:
                    away_from_key |= 1 << a
    return lost, away_from_key


@njit(cache=True)
def _axis_interlocking(contacts, a, n_parts, lost, away_from_key, base_ok, seen, stack):
    """The interlocking test on axis a of A_i, whose new piece has contacts both ways along a. When
    no contact of R was lost, the old nodes' graph is A_(i-1)'s, so where that was strongly connected
    (without the key), the new node's contacts (with nodes other than the key) decide."""
    if not lost:
        if base_ok[a, 0]:
            return True
        if base_ok[a, 1] and (away_from_key >> a) & 1 and (away_from_key >> (3 + a)) & 1:
            return True
    return _strongly_connected(contacts, a, n_parts, -1, -1, seen, stack) or _strongly_connected(
        contacts, a, n_parts, 0, -1, seen, stack
    )


@njit(cache=True)
def interlocking(chunk, n, nbr, part_of, r_node, in_chunk, contacts, base_ok, seen, stack, stamp):
    """The interlocking test on A_i, whose contacts are A_(i-1)'s with the chunk's moved from R to the
    new piece; `contacts` is changed for the test and restored, which is cheaper than a copy. Public for
    `compiled_checkers.check_chunk`, which runs it between its other checks; the chunk's voxels hold
    `stamp` in `in_chunk`, and `seen` and `stack` are work arrays of at least r_node + 1 entries."""
    if not _held_every_way(chunk, n, nbr, in_chunk, stamp):
        return False
    n_parts = r_node + 1
    lost, away_from_key = _move_contacts(chunk, n, nbr, part_of, r_node, in_chunk, contacts, stamp, 1)
    ok = True
    for a in range(3):
        if not _axis_interlocking(contacts, a, n_parts, lost, away_from_key, base_ok, seen, stack):
            ok = False
            break
    _move_contacts(chunk, n, nbr, part_of, r_node, in_chunk, contacts, stamp, -1)
    return ok
