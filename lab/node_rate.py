"""Lab study, outside the installed package.
Question: does a change to the search
cost node rate? (The search is the same node for node when only speed changed, so expansions per
second compare the cost of a node.)
Answer: docs/results.md; the measurements: docs/notebook/benchmarks.md,
"Record scale: 42,875 voxels and 2,000 pieces".

Node expansions per second of the plain search, this checkout against a baseline commit, side by side.

    .venv/bin/python lab/node_rate.py BASE_COMMIT [--rounds 3] [--seconds 20] [--task SHAPE:K ...]

Each task runs `rllock.search.solver.search` (seed 0, one core) for `--seconds` in a fresh process of
each tree, the two trees alternately, `--rounds` times; the medians of expansions per second and their
ratio are printed. The search is the same node for node in both trees when only speed changed (the
hash test says so), so the ratio is the cost of a node. The baseline is checked out in a temporary git
worktree and runs with this checkout's .venv.
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

log = logging.getLogger("node_rate")

ROOT = Path(__file__).resolve().parent.parent
TASKS = ("desia-bunny:100", "cube20:300", "cube35:1500")

ONE_RUN = """
import json, sys, time
from rllock.core.env import make_task
from rllock.search.solver import search
try:  # the search's counters moved to rllock.search.dfs; a baseline tree may be older
    from rllock.search.dfs import SearchStats
except ImportError:
    from rllock.search.solver import SearchStats
shape, pieces, seconds = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
task = make_task(shape, pieces)
next(search(make_task("cube4", 4), seed=0, time_limit=5), None)  # numba's cache, before the clock
stats = SearchStats()
start = time.perf_counter()
for _ in search(task, seed=0, time_limit=seconds, stats=stats):
    break
elapsed = time.perf_counter() - start
print(json.dumps({"voxels": task.size, "expansions": stats.expansions, "seconds": elapsed,
                  "placed": stats.placed}))
"""


def run_once(tree: Path, task: str, seconds: float) -> dict:
    shape, pieces = task.rsplit(":", 1)
    out = subprocess.run(
        [str(ROOT / ".venv/bin/python"), "-c", ONE_RUN, shape, pieces, str(seconds)],
        cwd=tree,
        env={"PYTHONPATH": str(tree), "PATH": "/usr/bin:/bin"},
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("base", help="the baseline commit")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--task", action="append", help=f"SHAPE:K (default {', '.join(TASKS)})")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp) / "base"
        subprocess.run(["git", "worktree", "add", "--detach", str(base), args.base], cwd=ROOT, check=True)
        try:
            for task in args.task or TASKS:
                rates: dict[str, list[float]] = {"base": [], "head": []}
                for r in range(args.rounds):
                    for kind, tree in (("base", base), ("head", ROOT)):
                        got = run_once(tree, task, args.seconds)
                        rates[kind].append(got["expansions"] / got["seconds"])
                        log.info("%s %s round %d: %s", task, kind, r + 1, got)
                b, h = statistics.median(rates["base"]), statistics.median(rates["head"])
                print(
                    f"{task} (N={got['voxels']}): baseline {args.base} {b:.1f} nodes/s "
                    f"{[round(x, 1) for x in rates['base']]}; this checkout {h:.1f} "
                    f"{[round(x, 1) for x in rates['head']]}; ratio {h / b:.2f}",
                    flush=True,
                )
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(base)], cwd=ROOT, check=False)


if __name__ == "__main__":
    sys.exit(main())
