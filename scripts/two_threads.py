"""Where one search on two threads loses against two cores, and what a portfolio adds (issue 34).

.venv/bin/python scripts/two_threads.py SHAPE_OR_MESH K [--resolution R] --seed S

The same search (the same seed, node for node) on one thread, on two (`search(threads=2)`), and as
`solve --workers 2` runs it (`portfolio_search`), one after another in this process. For the first two:
the seconds the samples took (summed over threads), the nodes whose children were sampled on the
threads and the wall time that took, the nodes sampled on the calling thread alone (one child), and the
samples run ahead for a guessed next node and how many of them the search took.
"""

import argparse
import logging
import time
from collections import Counter

from rllock.core.env import make_task
from rllock.core.shapes import load_shape
from rllock.search import solver
from rllock.search.portfolio import portfolio_search

log = logging.getLogger("two_threads")


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    parser = argparse.ArgumentParser()
    parser.add_argument("shape")
    parser.add_argument("pieces", type=int)
    parser.add_argument("--resolution", type=int, default=None)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--time-limit", type=float, default=60.0)
    args = parser.parse_args()
    task = make_task(load_shape(args.shape, args.resolution), args.pieces)
    next(solver.search(task, seed=args.seed + 1000, time_limit=1.0, threads=2), None)  # compile

    wall: Counter = Counter()
    calls: Counter = Counter()
    sample_all, chunks = solver._Expander.sample_all, solver._Expander._chunks

    def timed_sample_all(self, states, chunks):
        start = time.perf_counter()
        out = sample_all(self, states, chunks)
        where = "threads" if self.pool is not None and self.pool.worth_it(len(states)) else "alone"
        wall[where] += time.perf_counter() - start
        calls[where] += 1
        return out

    def timed_chunks(self, state, seed):
        start = time.perf_counter()
        out = chunks(self, state, seed)
        wall["samples"] += time.perf_counter() - start
        return out

    solver._Expander.sample_all, solver._Expander._chunks = timed_sample_all, timed_chunks
    for threads in (1, 2):
        wall.clear()
        calls.clear()
        pool = solver.SamplingPool.start(threads) if threads > 1 else None
        start = time.perf_counter()
        found = solver.search(task, seed=args.seed, time_limit=args.time_limit, pool=pool)
        got = next(found, None)
        seconds = time.perf_counter() - start
        found.close()
        log.info(
            "%d thread(s): %.2f s (%s); samples %.2f s; %d nodes on the threads %.2f s, %d alone %.2f s; "
            "samples run ahead %d, taken %d",
            threads, seconds, "found" if got else "none", wall["samples"], calls["threads"],
            wall["threads"], calls["alone"], wall["alone"],
            pool.guessed if pool else 0, pool.reused if pool else 0,
        )  # fmt: skip
        if pool is not None:
            pool.executor.shutdown()
    solver._Expander.sample_all, solver._Expander._chunks = sample_all, chunks
    start = time.perf_counter()
    found = portfolio_search(task, seed=args.seed, workers=2, time_limit=args.time_limit)
    got = next(found, None)
    found.close()
    log.info("solve --workers 2: %.2f s (%s)", time.perf_counter() - start, "found" if got else "none")


if __name__ == "__main__":
    main()
