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
Cells are parsed and timed as `rllock bench guide` does (`orchestration.bench.guide.parse_cells`,
`orchestration.bench.shapes.solver_cell`: each assembly verified). Prints a markdown row per cell:
seconds to the first valid assembly per seed (or `none in T (best p/K-1)`: the most pieces placed; the
tables in docs/benchmarks.md wrote it `none (p/K-1)`), and the ratio of the last arm's median to the
first's (an unsolved seed counts at the limit).
"""

from __future__ import annotations

import argparse
import logging

from orchestration.bench.guide import median_seconds, parse_cells
from orchestration.bench.shapes import solver_cell
from rllock.search.solver import SearchConfig

log = logging.getLogger("solver_arms")

ARMS = {
    "from30": SearchConfig(deep_from=30, remainder="cut", child_order="count"),
    "cut": SearchConfig(remainder="cut", child_order="count"),
    "surface": SearchConfig(remainder="surface", child_order="count"),
    "count": SearchConfig(child_order="count"),
    "default": SearchConfig(),
}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("cells", help="comma-separated SHAPE:K or SHAPE:K:path (a mesh as FILE@RESOLUTION:K)")
    p.add_argument("--arms", default="cut,surface", help=f"comma-separated, of {', '.join(ARMS)}")
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--time-limit", type=float, default=120.0)
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", force=True)
    seeds = [int(s) for s in args.seeds.split(",")]
    arms = {name: ARMS[name] for name in args.arms.split(",")}
    print(f"| cell | {' | '.join(arms)} | ratio of the medians |")
    print("|---|" + "---|" * (len(arms) + 1))
    for cell in parse_cells(args.cells):
        task = cell.task()
        results: dict[str, list] = {arm: [] for arm in arms}
        for seed in seeds:
            for arm, config in arms.items():
                results[arm].append(solver_cell(task, args.time_limit, seed, config=config))
                log.info("%s seed %d, %s: %s", cell.label, seed, arm, results[arm][-1].text(task.pieces))
        m = [median_seconds(r) for r in results.values()]
        cols = " | ".join(
            f"{', '.join(c.text(task.pieces) for c in results[a])}; {median:.1f}"
            for a, median in zip(arms, m)
        )
        print(f"| {cell.label} | {cols} | {m[-1] / m[0]:.2f} |", flush=True)


if __name__ == "__main__":
    main()
