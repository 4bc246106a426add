"""Variants of the search solver side by side in one process: the same cells and seeds, one arm after the
other per seed, one core.

The arms (`ARMS`): `from30`, deep mode from K = 30 with the smallest cuts (the default until 7162aef);
`cut`, deep mode at every K with the smallest cuts (until 6104197; still the judgement under path
removal); `surface`, the remainder's surface; these three try a node's children by the lookahead's
count; `count`, 6104197's default (the surface under straight removal, the cut under path removal,
children by count); `default`, `SearchConfig()` (children in the order of the remainder's judgement:
`SearchConfig.child_order`).

    python scripts/solver_arms.py sofa:19,cube4:9,cube6:25,ring:15 --arms from30,cut --time-limit 120
    python scripts/solver_arms.py sofa:19,mario:60 --arms cut,surface --time-limit 60
    python scripts/solver_arms.py spot.obj@24:163 --arms cut,surface   # a mesh at resolution 24

A cell is SHAPE:K or SHAPE:K:path, SHAPE a shape's name or a file, `@R` after it a mesh's resolution.
Prints a markdown row per cell: seconds to the first valid assembly per seed (or `none (p/K-1)`: the
most pieces placed), and the ratio of the last arm's median to the first's (an unsolved seed counts at
the limit).
"""

from __future__ import annotations

import argparse
import logging
import statistics
import time

from rllock.core.env import Task, make_task
from rllock.core.verifier import verify_labels
from rllock.search.solver import SearchConfig, SearchStats, search

log = logging.getLogger("solver_arms")

ARMS = {
    "from30": SearchConfig(deep_from=30, remainder="cut", child_order="count"),
    "cut": SearchConfig(remainder="cut", child_order="count"),
    "surface": SearchConfig(remainder="surface", child_order="count"),
    "count": SearchConfig(child_order="count"),
    "default": SearchConfig(),
}


def first_assembly(task: Task, seed: int, limit: float, config: SearchConfig) -> tuple[float | None, int]:
    """(seconds or None, pieces placed at best) of one search, its assembly checked by the verifier."""
    stats = SearchStats()
    start = time.monotonic()
    found = next(search(task, seed=seed, time_limit=limit, config=config, stats=stats), None)
    seconds = time.monotonic() - start
    if found is not None and not verify_labels(found.labels, task.removal).valid:
        raise AssertionError("the search returned an assembly the verifier rejects")
    return (None if found is None else seconds), stats.placed


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("cells", help="comma-separated SHAPE:K or SHAPE:K:path")
    p.add_argument("--arms", default="cut,surface", help=f"comma-separated, of {', '.join(ARMS)}")
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--time-limit", type=float, default=120.0)
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", force=True)
    seeds = [int(s) for s in args.seeds.split(",")]
    arms = {name: ARMS[name] for name in args.arms.split(",")}
    print(f"| cell | {' | '.join(arms)} | ratio of the medians |")
    print("|---|" + "---|" * (len(arms) + 1))
    for cell in args.cells.split(","):
        parts = cell.split(":")
        removal = parts.pop() if parts[-1] in ("straight", "path") else "straight"
        k = parts.pop()
        shape, _, resolution = ":".join(parts).partition("@")  # box:AxBxC holds a colon
        task = make_task(shape, int(k), removal, resolution=int(resolution) if resolution else None)
        texts: dict[str, list[str]] = {arm: [] for arm in arms}
        medians: dict[str, list[float]] = {arm: [] for arm in arms}
        for seed in seeds:
            for arm, config in arms.items():
                seconds, placed = first_assembly(task, seed, args.time_limit, config)
                text = f"none ({placed}/{int(k) - 1})" if seconds is None else f"{seconds:.1f}"
                log.info("%s seed %d, %s: %s", cell, seed, arm, text)
                texts[arm].append(text)
                medians[arm].append(args.time_limit if seconds is None else seconds)
        m = [statistics.median(v) for v in medians.values()]
        cols = " | ".join(f"{', '.join(texts[a])}; {median:.1f}" for a, median in zip(arms, m, strict=True))
        print(f"| {cell} | {cols} | {m[-1] / m[0]:.2f} |", flush=True)


if __name__ == "__main__":
    main()
