"""How busy `solve --workers 2` keeps worker 0's sampling threads, second by second (issue 34).

.venv/bin/python scripts/busy_share.py SHAPE_OR_MESH K [--resolution R] [--removal path] --seed S

Runs the portfolio as `solve --workers 2` does, but with worker 0 keeping both cores throughout, and logs
every second the share of the time its threads were busy since the lent worker started up (the CPU
seconds of the samples begun since, over the wall time, over the threads): the figure
`rllock.search.portfolio` judges by.
"""

import argparse
import logging
import time

from rllock.core.env import make_task
from rllock.core.shapes import load_shape
from rllock.search import portfolio

log = logging.getLogger("busy_share")


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    logging.getLogger("rllock.search.portfolio").setLevel(logging.DEBUG)
    parser = argparse.ArgumentParser()
    parser.add_argument("shape")
    parser.add_argument("pieces", type=int)
    parser.add_argument("--resolution", type=int, default=None)
    parser.add_argument("--removal", default="straight")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--seconds", type=float, default=9.0)
    args = parser.parse_args()
    task = make_task(load_shape(args.shape, args.resolution), args.pieces, removal=args.removal)
    portfolio.KEEP_WHILE_BUSY = 0.0  # keep the cores: every second's share is logged
    start = time.monotonic()
    found = portfolio.portfolio_search(task, seed=args.seed, workers=2, time_limit=args.seconds)
    got = next(found, None)
    found.close()
    log.info("%.1f s, %s", time.monotonic() - start, "found" if got else "none")


if __name__ == "__main__":
    main()
