"""The compiled checkers: the three checks on raw chunks for piece i of a state (numba).

The sampler that draws the chunks is `compiled_sampler`; `reference_checkers` is the plain version
that these are tested against (tests/test_compiled.py).

A state is per-voxel labels (int16[N]): 0 for the remaining volume R, j for piece Pj. The checkers
here assume what every state reached through accepted chunks satisfies: R_(i-1) is connected and so
are the placed pieces (chunks are connected by construction).

Work per search node is split in two. `_prepare` runs once per node and builds incremental state:
  - part_of[v]: blocking-graph node of each voxel (pieces 0..i-2, new piece i-1, R = i);
  - ray_r[v, k]: how many R_(i-1) voxels lie strictly beyond v along direction k;
  - contacts: face contacts along each +axis in A_(i-1), those of R and of the new piece as counts
    per node, those between placed pieces as adjacency lists (`_contacts`: sparse, since a piece
    touches few others and K reaches thousands), and base_ok: per axis, whether A_(i-1)'s graph is
    strongly connected (without the key);
  - r_nbr[v]: the R_(i-1) neighbours of each R_(i-1) voxel, which the sampler grows chunks over.
Per chunk, the checks then cost O(n) (plus searches that stop early, below):
  - removable along k iff sum over chunk voxels of ray_r == pairs of chunk voxels sharing a k-line,
    because each such pair puts exactly one chunk voxel (a former R voxel) beyond the other;
  - connected: R_i is connected iff all R_i voxels touching the chunk are in one component of R_i
    (every R_i voxel reaches the chunk's boundary inside R_(i-1), so it reaches that component);
    searches from each of them merge as they meet, so the test ends at the first cut-off component;
  - interlocking: the new piece must touch the shape in all 6 directions; the contact counts of A_i
    are those of A_(i-1) with the chunk's contacts moved from R to the new piece; where R lost no
    contact and A_(i-1) was strongly connected on an axis, the new piece's contacts decide, and
    otherwise an SCC test runs on that axis.
Checks run in the order that rejects most per unit of work (straight removability, interlocking,
connectivity) and stop at the first failure.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from rllock.core import numba_cache  # noqa: F401  (before any @njit: it picks the cache folder)

CONNECTED, REMOVABLE, INTERLOCKING = 1, 2, 4
ALL_CHECKS = CONNECTED | REMOVABLE | INTERLOCKING
# Rows of `_contacts`' counts: an out row and its in row are one apart, so that a search against the
# edges (direction 1) reads row + 1 where one along them (direction 0) reads row, or row - 1 for an IN.
R_OUT, R_IN, NEW_OUT, NEW_IN = 0, 1, 2, 3


@njit(cache=True)
def prepare_node(nbr, ray, labels, piece):
    n_vox = labels.shape[0]
    r_node = piece
    n_parts = piece + 1
    part_of = np.empty(n_vox, np.int32)
    for v in range(n_vox):
        part_of[v] = r_node if labels[v] == 0 else labels[v] - 1
    seeds = np.empty(n_vox, np.int32)
    n_seeds = 0
    for v in range(n_vox):
        if part_of[v] != r_node:
            continue
        if piece == 1:
            seeds[n_seeds] = v
            n_seeds += 1
            continue
        for k in range(6):
            u = nbr[v, k]
            if u >= 0 and labels[u] == piece - 1:
                seeds[n_seeds] = v
                n_seeds += 1
                break
    ray_r = _rays_in_r(ray, part_of, r_node)
    contacts = _contacts(nbr, part_of, n_parts)
    base_ok = _base_interlocking(contacts, n_parts) if piece > 1 else np.zeros((3, 2), np.bool_)
    r_nbr = np.full((n_vox, 6), -1, np.int32)
    for v in range(n_vox):
        if part_of[v] != r_node:
            continue
        d = 0
        for k in range(6):
            u = nbr[v, k]
            if u >= 0 and part_of[u] == r_node:
                r_nbr[v, d] = u
                d += 1
    return part_of, seeds[:n_seeds], ray_r, contacts, base_ok, r_nbr


@njit(cache=True)
def _rays_in_r(ray, part_of, r_node):
    """ray_r[v, k]: how many R voxels lie strictly beyond v along direction k, in one sweep per
    direction: voxels are numbered in [x, y, z] order, so the next voxel along a + direction has a
    higher number (a - direction, lower), and its count is known before v's."""
    n_vox = part_of.shape[0]
    ray_r = np.zeros((n_vox, 6), np.int32)
    for k in range(6):
        for i in range(n_vox):
            v = n_vox - 1 - i if k % 2 == 0 else i
            u = ray[v, k]
            if u >= 0:
                ray_r[v, k] = ray_r[u, k] + (part_of[u] == r_node)
    return ray_r


@njit(cache=True)
def _contacts(nbr, part_of, n_parts):
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


@njit(cache=True)
def _straight_free(chunk, n, line, ray_r, line_count):
    """Bitmask over the 6 directions along which the chunk slides out of R_i."""
    free = 0
    for a in range(3):
        pairs = 0
        for j in range(n):
            lid = line[chunk[j], a]
            pairs += line_count[lid]
            line_count[lid] += 1
        for j in range(n):
            line_count[line[chunk[j], a]] = 0
        for s in range(2):
            k = 2 * a + s
            total = 0
            for j in range(n):
                total += ray_r[chunk[j], k]
            if total == pairs:
                free |= 1 << k
    return free


@njit(cache=True)
def _find(parent, g):
    while parent[g] != g:
        parent[g] = parent[parent[g]]
        g = parent[g]
    return g


@njit(cache=True)
def _remaining_connected(chunk, n, nbr, part_of, r_node, in_chunk, mark, owner, nxt, groups, stamp):
    """R_i connected, given R_(i-1) connected: whether the R_i voxels touching the chunk are in one
    component of R_i. One breadth-first search grows from each of them, in turns, and searches that
    meet are merged (union-find), so the test ends when all have met, or when the searches of one
    merged group run out of voxels: that group then fills a component that misses another boundary
    voxel. Either way it ends early: a failure costs about the size of the smallest component cut
    off, a success the distance between neighbouring boundary voxels, not a walk over all of R_i.
    `mark[v] == stamp` once v is reached, `owner[v]` is the search that reached it and `nxt` links
    each search's queue; groups rows: union-find parent, queue head, queue tail, live searches."""
    parent, head, tail, alive = groups[0], groups[1], groups[2], groups[3]
    nb = 0
    for j in range(n):
        v = chunk[j]
        for k in range(6):
            u = nbr[v, k]
            if u >= 0 and part_of[u] == r_node and in_chunk[u] != stamp and mark[u] != stamp:
                mark[u] = stamp
                owner[u] = nb
                nxt[u] = -1
                parent[nb] = nb
                head[nb] = u
                tail[nb] = u
                alive[nb] = 1
                nb += 1
    if nb == 0:
        return False
    roots = nb
    while roots > 1:
        for g in range(nb):
            v = head[g]
            if v < 0:
                continue
            head[g] = nxt[v]
            for k in range(6):
                u = nbr[v, k]
                if u < 0 or part_of[u] != r_node or in_chunk[u] == stamp:
                    continue
                if mark[u] != stamp:
                    mark[u] = stamp
                    owner[u] = g
                    nxt[u] = -1
                    if head[g] < 0:
                        head[g] = u
                    else:
                        nxt[tail[g]] = u
                    tail[g] = u
                    continue
                a = _find(parent, g)
                b = _find(parent, owner[u])
                if a != b:
                    parent[b] = a
                    alive[a] += alive[b]
                    roots -= 1
                    if roots == 1:
                        return True
            if head[g] < 0:
                a = _find(parent, g)
                alive[a] -= 1
                if alive[a] == 0:
                    return False
    return True


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
def _base_interlocking(contacts, n_parts):
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
def _interlocking(chunk, n, nbr, part_of, r_node, in_chunk, contacts, base_ok, seen, stack, stamp):
    """The interlocking test on A_i, whose contacts are A_(i-1)'s with the chunk's moved from R to the
    new piece; `contacts` is changed for the test and restored, which is cheaper than a copy."""
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


@njit(cache=True)
def _path_free(chunk, n, coords, index, part_of, r_node, in_chunk, visited, queue, stamp):
    """DESIA's removability: BFS over integer offsets of collision-free unit moves until the chunk
    is outside the canvas (equivalent to leaving R_i's bounding box: from there it slides away)."""
    gx, gy, gz = index.shape
    lo = np.empty(3, np.int64)
    hi = np.empty(3, np.int64)
    for a in range(3):
        lo[a] = coords[chunk[0], a]
        hi[a] = coords[chunk[0], a]
    for j in range(1, n):
        for a in range(3):
            c = coords[chunk[j], a]
            lo[a] = min(lo[a], c)
            hi[a] = max(hi[a], c)
    sy, sz = 2 * gy + 1, 2 * gz + 1
    queue[0] = (gx * sy + gy) * sz + gz  # offset (0, 0, 0)
    visited[queue[0]] = stamp
    head, tail = 0, 1
    while head < tail:
        code = queue[head]
        head += 1
        oz = code % sz - gz
        oy = (code // sz) % sy - gy
        ox = code // (sy * sz) - gx
        if (
            hi[0] + ox < 0
            or lo[0] + ox >= gx
            or hi[1] + oy < 0
            or lo[1] + oy >= gy
            or hi[2] + oz < 0
            or lo[2] + oz >= gz
        ):
            return True
        for k in range(6):
            dx = (1 if k == 0 else -1 if k == 1 else 0) + ox
            dy = (1 if k == 2 else -1 if k == 3 else 0) + oy
            dz = (1 if k == 4 else -1 if k == 5 else 0) + oz
            nxt = ((dx + gx) * sy + dy + gy) * sz + dz + gz
            if visited[nxt] == stamp:
                continue
            visited[nxt] = stamp
            blocked = False
            for j in range(n):
                x = coords[chunk[j], 0] + dx
                y = coords[chunk[j], 1] + dy
                z = coords[chunk[j], 2] + dz
                if 0 <= x < gx and 0 <= y < gy and 0 <= z < gz:
                    u = index[x, y, z]
                    if u >= 0 and part_of[u] == r_node and in_chunk[u] != stamp:
                        blocked = True
                        break
            if not blocked:
                queue[tail] = nxt
                tail += 1
    return False


@njit(cache=True, inline="always")
def check_chunk(chunk, n, piece, topo, node, removal_path, full, scratch, stamp):
    """Bitmask of passed checks (CONNECTED | REMOVABLE | INTERLOCKING). With `full` false it stops at
    the first failure and returns 0 for any rejected chunk. The chunk's voxels hold `stamp` in
    scratch's `in_chunk`."""
    nbr, _, line, _, coords, index = topo
    part_of, _, ray_r, contacts, base_ok, _ = node
    in_chunk, mark, owner, nxt, groups, line_count, seen, stack, visited, off_queue = scratch
    r_node = piece
    result = 0
    removable = _straight_free(chunk, n, line, ray_r, line_count) != 0
    if not removable and not removal_path and not full:
        return 0
    # Interlocking before connectivity: its first test rejects most chunks for a few loads each.
    if piece == 1 or _interlocking(
        chunk, n, nbr, part_of, r_node, in_chunk, contacts, base_ok, seen, stack, stamp
    ):
        result |= INTERLOCKING
    elif not full:
        return 0
    if _remaining_connected(chunk, n, nbr, part_of, r_node, in_chunk, mark, owner, nxt, groups, stamp):
        result |= CONNECTED
    elif not full:
        return 0
    if not removable and removal_path:
        removable = _path_free(chunk, n, coords, index, part_of, r_node, in_chunk, visited, off_queue, stamp)
    if removable:
        result |= REMOVABLE
    return result


@njit(cache=True)
def scratch_arrays(n_vox, n_lines, n_parts, dims, removal_path):
    """Work arrays of `check_chunk`: (in_chunk, mark, owner, nxt, groups, line_count, seen, stack, visited,
    off_queue). Stamped arrays start at 0 and stamps at 1, so they never need clearing. The offset
    arrays of path removal (one entry per translation within the canvas: 357,911 at 35^3) are made
    only for it."""
    n_off = (2 * dims[0] + 1) * (2 * dims[1] + 1) * (2 * dims[2] + 1) if removal_path else 1
    return (
        np.zeros(n_vox, np.int64),
        np.zeros(n_vox, np.int64),
        np.empty(n_vox, np.int32),
        np.empty(n_vox, np.int32),
        np.empty((4, n_vox), np.int32),
        np.zeros(n_lines, np.int32),
        np.zeros(n_parts, np.bool_),
        np.empty(n_parts, np.int32),
        np.zeros(n_off, np.int64),
        np.empty(n_off, np.int64),
    )


@njit(cache=True)
def check_chunks(topo, labels, piece, chunks, removal_path):
    """Every check on every given chunk (no early exit): int32 bitmask per chunk. For testing."""
    nbr, ray, _, n_lines, _, index = topo
    node = prepare_node(nbr, ray, labels, piece)
    scratch = scratch_arrays(labels.shape[0], n_lines, piece + 1, index.shape, removal_path)
    in_chunk = scratch[0]
    out = np.zeros(chunks.shape[0], np.int32)
    n = chunks.shape[1]
    for s in range(chunks.shape[0]):
        stamp = s + 1
        for j in range(n):
            in_chunk[chunks[s, j]] = stamp
        out[s] = check_chunk(chunks[s], n, piece, topo, node, removal_path, True, scratch, stamp)
    return out
