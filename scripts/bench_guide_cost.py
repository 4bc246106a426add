"""The guide network's cost per evaluation at three shape sizes (issue 33): one search node's children
(8 states after one piece) encoded and evaluated in one call, median over repeats, one core.

    .venv/bin/python scripts/bench_guide_cost.py [--guide CHECKPOINT] [--repeats 50]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import jax
import numpy as np

from rllock.config import GuideConfig
from rllock.core.env import apply_chunk, initial_state, make_task, sample_accepted
from rllock.search.guide import Guide, encode, guide_values, init_guide
from rllock.search.guide_checkpoint import load_guide

SHAPES = (("box:8x8x8", 50), ("box:17x17x17", 500), ("cube35", 4000))  # N = 512, 4,913, 42,875


def children(shape: str, pieces: int, count: int = 8):
    task = make_task(shape, pieces)
    root = initial_state(task)
    for seed in range(100):
        chunks = sample_accepted(task, root, seed=seed, num_samples=4096)
        if len(chunks) >= count:
            return task, [apply_chunk(root, c) for c in chunks[:count]]
    raise SystemExit(f"no {count} first pieces found for {shape}")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--guide", default=None, help="default: an untrained guide of the default size")
    parser.add_argument("--repeats", type=int, default=50)
    args = parser.parse_args()
    config = GuideConfig()
    guide = (
        load_guide(args.guide)
        if args.guide
        else Guide(config, init_guide(config, jax.random.PRNGKey(0)), "untrained")
    )
    rows = []
    for shape, pieces in SHAPES:
        task, states = children(shape, pieces)
        shares = [1.0] * len(states)
        guide.values(task, states, shares)  # compile
        encode_s, network_s = [], []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            e = encode(task, states, shares, guide.config)
            t1 = time.perf_counter()
            np.asarray(guide_values(guide.params, e.window, e.features, config=guide.config))
            network_s.append(time.perf_counter() - t1)
            encode_s.append(t1 - t0)
        per = len(states)
        rows.append(
            {
                "shape": shape,
                "voxels": task.size,
                "states_per_call": per,
                "encode_ms_per_state": 1000 * statistics.median(encode_s) / per,
                "network_ms_per_state": 1000 * statistics.median(network_s) / per,
            }
        )
        print(json.dumps(rows[-1]))


if __name__ == "__main__":
    main()
