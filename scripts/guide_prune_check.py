"""Why the trained guide is slower on easy cells: the same guide without pruning, and with the count
share first. Seeds 0-2, ring K=15 and cube6 K=25, 30 s limit, one process (one core)."""

import sys
import time

from rllock.core.env import make_task
from rllock.search.guide_checkpoint import load_guide
from rllock.search.solver import SearchConfig, search

g = load_guide(sys.argv[1] if len(sys.argv) > 1 else "runs/guide-cpu")
arms = {
    "solver": (None, SearchConfig()),
    "guided (default: prune 0.02, count 0.5)": (g, SearchConfig()),
    "guided, no pruning": (g, SearchConfig(prune_below=0.0)),
    "guided, no pruning, count weight 2": (g, SearchConfig(prune_below=0.0, guide_count_weight=2.0)),
}
for shape, k in (("ring", 15), ("cube6", 25)):
    task = make_task(shape, k)
    for name, (guide, config) in arms.items():
        times, pruned = [], []
        for seed in range(3):
            t0 = time.perf_counter()
            found = next(search(task, seed=seed, time_limit=30, config=config, guide=guide), None)
            times.append(round(time.perf_counter() - t0, 1) if found is not None else None)
        print(f"{shape} K={k} | {name} | {times}", flush=True)
