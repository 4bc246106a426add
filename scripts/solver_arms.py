"""Deep mode at every K against deep mode from K = 30 (the former default), side by side in one process.

The search solver's deep mode (wide seeds, thin growth, children with the smallest cut, longer restarts;
`SearchConfig.deep_from`) was the default from K = 30 on. Here both thresholds run on the same cells and
seeds, one after the other per seed, one core:

    python scripts/deep_mode.py sofa:19,cube4:9,cube6:25,ring:15 --time-limit 120
    python scripts/deep_mode.py spider:20,cube4:8,box:6x5x4:12:path --time-limit 120

A cell is SHAPE:K or SHAPE:K:path. Prints a markdown row per cell: seconds to the first valid assembly
per seed (or `none (p/K-1)`: the most pieces placed), and the ratio of the medians (an unsolved seed
counts at the limit).
"""

from __future__ import annotations

import argparse
import logging
import statistics
import time

from rllock.core.env import make_task
from rllock.core.verifier import verify_labels
from rllock.search.solver import SearchConfig, SearchStats, search

log = logging.getLogger("deep_mode")

ARMS = {"deep from K = 30": SearchConfig(deep_from=30), "deep at every K": SearchConfig(deep_from=2)}


def first_assembly(shape: str, k: int, removal: str, seed: int, limit: float, config: SearchConfig):
    """(seconds or None, pieces placed at best) of one search, its assembly checked by the verifier."""
    task = make_task(shape, k, removal)
    stats = SearchStats()
    start = time.monotonic()
    found = next(search(task, seed=seed, time_limit=limit, config=config, stats=stats), None)
    seconds = time.monotonic() - start
    if found is not None and not verify_labels(found.labels, removal).valid:
        raise AssertionError("the search returned an assembly the verifier rejects")
    return (None if found is None else seconds), stats.placed


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("cells", help="comma-separated SHAPE:K or SHAPE:K:path")
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--time-limit", type=float, default=120.0)
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", force=True)
    seeds = [int(s) for s in args.seeds.split(",")]
    print(f"| cell | {' | '.join(ARMS)} | ratio of the medians |")
    print("|---|" + "---|" * (len(ARMS) + 1))
    for cell in args.cells.split(","):
        parts = cell.split(":")
        removal = parts.pop() if parts[-1] in ("straight", "path") else "straight"
        k = parts.pop()
        shape = ":".join(parts)  # box:AxBxC holds a colon
        texts: dict[str, list[str]] = {arm: [] for arm in ARMS}
        medians: dict[str, list[float]] = {arm: [] for arm in ARMS}
        for seed in seeds:
            for arm, config in ARMS.items():
                seconds, placed = first_assembly(shape, int(k), removal, seed, args.time_limit, config)
                text = f"none ({placed}/{int(k) - 1})" if seconds is None else f"{seconds:.1f}"
                log.info("%s seed %d, %s: %s", cell, seed, arm, text)
                texts[arm].append(text)
                medians[arm].append(args.time_limit if seconds is None else seconds)
        m = {arm: statistics.median(v) for arm, v in medians.items()}
        old, new = m.values()
        cols = " | ".join(f"{', '.join(texts[a])}; {m[a]:.1f}" for a in ARMS)
        print(f"| {cell} | {cols} | {new / old:.2f} |", flush=True)


if __name__ == "__main__":
    main()
