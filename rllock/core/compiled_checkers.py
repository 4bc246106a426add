"""The compiled checkers: the three checks on raw chunks for piece i of a state (numba).

The sampler that draws the chunks is `compiled_sampler`; `reference_checkers` is the plain version
that these are tested against (tests/test_compiled.py). The interlocking check and the contact graph it
reads are in `compiled_interlocking`; removability and the connectivity of the rest are here.

A state is per-voxel labels (int16[N]): 0 for the remaining volume R, j for piece Pj. The checkers
here assume what every state reached through accepted chunks satisfies: R_(i-1) is connected and so
are the placed pieces (chunks are connected by construction).

Work per search node is split in two. `prepare_node` runs once per node and builds incremental state:
  - part_of[v]: blocking-graph node of each voxel (pieces 0..i-2, new piece i-1, R = i);
  - ray_r[v, k]: how many R_(i-1) voxels lie strictly beyond v along direction k;
  - contacts and base_ok: A_(i-1)'s contact graph per axis and whether it is strongly connected
    (`compiled_interlocking.contact_graph`, `compiled_interlocking.base_interlocking`);
  - r_nbr[v]: the R_(i-1) neighbours of each R_(i-1) voxel, which the sampler grows chunks over.
Per chunk, the checks then cost O(n) (plus searches that stop early, below):
  - removable along k iff sum over chunk voxels of ray_r == pairs of chunk voxels sharing a k-line,
    because each such pair puts exactly one chunk voxel (a former R voxel) beyond the other;
  - connected: R_i is connected iff all R_i voxels touching the chunk are in one component of R_i
    (every R_i voxel reaches the chunk's boundary inside R_(i-1), so it reaches that component);
    searches from each of them merge as they meet, so the test ends at the first cut-off component;
  - interlocking: `compiled_interlocking.interlocking`, which moves the chunk's contacts from R to the
    new piece and tests strong connectivity only where that can have changed.
Checks run in the order that rejects most per unit of work (straight removability, interlocking,
connectivity) and stop at the first failure.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from rllock.core import numba_cache  # noqa: F401  (before any @njit: it picks the cache folder)
from rllock.core.compiled_interlocking import base_interlocking, contact_graph, interlocking

CONNECTED, REMOVABLE, INTERLOCKING = 1, 2, 4
ALL_CHECKS = CONNECTED | REMOVABLE | INTERLOCKING


@njit(cache=True)
def prepare_node(nbr, ray, labels, piece):
    """The incremental state of a search node for sampling and checking piece `piece` (module
    docstring): (part_of, seeds, ray_r, contacts, base_ok, r_nbr), where seeds are the R voxels that
    touch the previous piece (every R voxel for the first), the voxels its chunks grow from."""
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
    contacts = contact_graph(nbr, part_of, n_parts)
    base_ok = base_interlocking(contacts, n_parts) if piece > 1 else np.zeros((3, 2), np.bool_)
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
    if piece == 1 or interlocking(
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
