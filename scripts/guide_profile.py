"""Where a guided search spends its time: cProfile of desia-dog K=60, seed 0, 30 s (issue 33).

.venv/bin/python scripts/guide_profile.py [GUIDE]
"""

import cProfile
import io
import pstats
import sys

from rllock.core.env import make_task
from rllock.search.guide_checkpoint import load_guide
from rllock.search.solver import SearchStats, search

g = load_guide(sys.argv[1] if len(sys.argv) > 1 else "runs/guide-cpu")
task = make_task("desia-dog", 60)
next(search(make_task("cube4", 7), seed=0, time_limit=10, guide=g), None)  # compile outside the profile
stats = SearchStats()
pr = cProfile.Profile()
pr.enable()
next(search(task, seed=0, time_limit=30, guide=g, stats=stats), None)
pr.disable()
s = io.StringIO()
p = pstats.Stats(pr, stream=s)
p.sort_stats("cumulative").print_stats(25)
total = p.total_tt
print("expansions", stats.expansions, "total s", round(total, 1))
for name in (
    "sample_accepted",
    "tightest_subset",
    "values",
    "encode",
    "guide_values",
    "apply_chunk",
    "distinct_subset",
):
    hits = [(v[3], k) for k, v in p.stats.items() if k[2] == name]
    if hits:
        ct = max(hits)[0]
        print(f"{name}: {ct:.2f} s ({100 * ct / total:.0f}%)")
