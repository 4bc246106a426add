"""Where is a failed search's failure set? (issue 33, an analysis)

Runs the search solver on a task; if it fails, takes the deepest state it reached and walks back along its
pieces: from each prefix (the first d pieces of that state) an exact search tries every accepted chunk
(every connected n-voxel subset of the remaining volume, enumerated exhaustively and checked by the
compiled checkers), until a prefix is found from which an assembly exists, or a prefix's exact search
runs out of its node budget. A prefix whose exact search fails is dead whatever a search does below it,
so the failure was set at a shallower piece; and a node where the exhaustive enumeration accepts chunks
that the sampler never draws would show the sampler, not the judgement, at fault.

    python scripts/exact_tail.py sofa 19 --seed 0 --seconds 20 --budget 200
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np

from rllock.core import compiled_checkers as checkers
from rllock.core.compiled_sampler import distinct_rows
from rllock.core.env import State, Task, apply_chunk, make_task, sample_accepted
from rllock.search.solver import SearchStats, search

log = logging.getLogger("exact_tail")


def connected_subsets(nbr: np.ndarray, region: np.ndarray, n: int) -> list[list[int]]:
    """Every connected n-subset of the voxels `region` (face neighbours `nbr`), each once (Wernicke's ESU:
    a subset is grown from its smallest voxel, through voxels larger than it that are new neighbours)."""
    inside = set(int(v) for v in region)
    out: list[list[int]] = []

    def grow(subset: list[int], extension: list[int], root: int) -> None:
        if len(subset) == n:
            out.append(sorted(subset))
            return
        around = {int(u) for s in subset for u in nbr[s] if u >= 0}
        extension = list(extension)
        while extension:
            w = extension.pop()
            more = [
                int(u)
                for u in nbr[w]
                if u > root and u in inside and u not in around and u not in subset and u not in extension
            ]
            grow([*subset, w], extension + more, root)

    for v in sorted(inside):
        grow([v], [int(u) for u in nbr[v] if u > v and u in inside], v)
    return out


def accepted_chunks(task: Task, state: State) -> tuple[np.ndarray, int]:
    """(every accepted chunk of the next piece, the number of connected chunks enumerated)."""
    chunks = connected_subsets(task.topology.nbr, np.flatnonzero(state.labels == 0), task.piece_size)
    if not chunks:
        return np.zeros((0, task.piece_size), np.int32), 0
    rows = np.asarray(chunks, np.int32)
    passed = checkers.check_chunks(
        task.topology.arrays, state.labels, state.placed + 1, rows, task.removal == "path"
    )
    return rows[passed == checkers.ALL_CHECKS], len(rows)


def exact(task: Task, state: State, budget: int) -> tuple[bool | None, int]:
    """(True: an assembly exists below `state`; False: none does; None: `budget` nodes ran out), nodes."""
    target, nodes = task.pieces - 1, [0]

    def below(s: State) -> bool:
        if s.placed == target:
            return True
        nodes[0] += 1
        if nodes[0] > budget:
            raise TimeoutError
        return any(below(apply_chunk(s, c)) for c in accepted_chunks(task, s)[0])

    try:
        return below(state), nodes[0]
    except TimeoutError:
        return None, nodes[0]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("shape")
    p.add_argument("pieces", type=int)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--seconds", type=float, default=20.0, help="the search's time limit")
    p.add_argument("--budget", type=int, default=200, help="nodes of each prefix's exact search")
    p.add_argument("--samples", type=int, default=200_000, help="sampler draws at the deepest state")
    args = p.parse_args()
    task = make_task(args.shape, args.pieces)
    stats = SearchStats()
    if next(search(task, seed=args.seed, time_limit=args.seconds, stats=stats), None) is not None:
        log.info("the search solved it: nothing to analyse")
        return
    deepest = stats.deepest
    assert deepest is not None
    accepted, enumerated = accepted_chunks(task, deepest)
    drawn = sample_accepted(task, deepest, seed=args.seed, num_samples=args.samples, closed_share=0.5)
    log.info(
        "deepest state: %d of %d pieces, %d voxels left; %d connected %d-voxel chunks, %d accepted; "
        "the sampler accepted %d distinct in %d draws",
        deepest.placed,
        task.pieces - 1,
        int((deepest.labels == 0).sum()),
        enumerated,
        task.piece_size,
        len(accepted),
        len(distinct_rows(drawn)),
        args.samples,
    )
    for d in range(deepest.placed, -1, -1):
        prefix = State(np.where(deepest.labels <= d, deepest.labels, 0).astype(deepest.labels.dtype), d)
        start = time.perf_counter()
        result, nodes = exact(task, prefix, args.budget)
        verdict = {True: "an assembly exists", False: "dead", None: "undecided"}[result]
        log.info(
            "from its first %d pieces: %s (%d nodes, %.1f s)", d, verdict, nodes, time.perf_counter() - start
        )
        if result is not False:
            break


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s", force=True)  # an import set a root handler
    main()
