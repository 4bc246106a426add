"""Where a guided search spends its time: cProfile of one `solve --guide` search (issue 33), and the
seconds and node expansions of its two sequences of restarts, the solver's and the diving ones
(`SearchConfig.dive_share`).

.venv/bin/python scripts/guide_profile.py [CELL] [GUIDE] [SECONDS] [SEED]
    CELL as `rllock bench guide --cells` writes it (default mario:60), GUIDE a train-guide run or
    checkpoint (default: the shipped guide), until the first assembly or SECONDS (default 60)
"""

import cProfile
import io
import pstats
import sys
import time

from rllock.core.env import initial_state
from rllock.search import solver
from rllock.search.curriculum import parse_named_task
from rllock.search.guide_checkpoint import load_guide
from rllock.search.solver import SearchStats, search

args = sys.argv[1:] + [None] * 4
cell, path, seconds, seed = args[0] or "mario:60", args[1], float(args[2] or 60), int(args[3] or 0)
g = load_guide(path) if path else load_guide()
task = parse_named_task(cell).task()
g.values(task, [initial_state(task)], [1.0])  # the network compiled outside the profile (one batch shape)
next(search(task, seed=seed, time_limit=2), None)  # and the compiled checkers loaded

# Each restart's seconds and expansions, by sequence: a diving restart is its dives (`_best_dive`) and
# the DFS from the dive state that follows them.
spent = {"solver": [0.0, 0], "diving": [0.0, 0]}
diving, inside = [False], [False]
best_dive, dfs = solver._best_dive, solver._dfs


def timed_best_dive(*a, **k):
    began, inside[0] = time.monotonic(), True
    try:
        begin, used = best_dive(*a, **k)
    finally:
        inside[0] = False
    spent["diving"][0] += time.monotonic() - began
    spent["diving"][1] += used
    diving[0] = True
    return begin, used


def timed_dfs(*a, **k):
    if inside[0]:
        return dfs(*a, **k)
    began = time.monotonic()
    state, used = dfs(*a, **k)
    which = "diving" if diving[0] else "solver"
    spent[which][0] += time.monotonic() - began
    spent[which][1] += used
    diving[0] = False
    return state, used


solver._best_dive, solver._dfs = timed_best_dive, timed_dfs
stats = SearchStats()
pr = cProfile.Profile()
pr.enable()
found = next(search(task, seed=seed, time_limit=seconds, guide=g, stats=stats), None)
pr.disable()
s = io.StringIO()
p = pstats.Stats(pr, stream=s)
p.sort_stats("cumulative").print_stats(25)
total = p.total_tt
print(s.getvalue())
print(
    f"{cell} seed {seed}: {'found' if found else 'none'}, expansions {stats.expansions}, restarts"
    f" {stats.restarts} ({stats.dives} dived), total {total:.1f} s (under the profiler)"
)
for which, (secs, used) in spent.items():
    print(f"{which} restarts: {secs:.1f} s, {used} expansions, {1000 * secs / max(used, 1):.2f} ms each")
for name in ("sample_accepted", "tightest_subset", "values", "encode", "guide_values", "apply_chunk"):
    hits = [(v[3], k) for k, v in p.stats.items() if k[2] == name]
    if hits:
        ct = max(hits)[0]
        print(f"{name}: {ct:.2f} s ({100 * ct / total:.0f}%)")
