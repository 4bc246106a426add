"""The guide network's cost per evaluation at three shape sizes (issue 33): one search node's children
(8 states after one piece) encoded and evaluated in one call, median over repeats, one core.

    .venv/bin/python scripts/bench_guide_cost.py [--guide CHECKPOINT] [--repeats 50] [--left L]

`--left L`: instead, 8 states with L pieces left, where the guide judges (its horizon): R the L x n
voxels nearest a point (a different point per state), the rest placed pieces, the last of them the next
n voxels out. Not states a search reaches, but what the encoding's cost depends on: N and R's box.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import jax
import numpy as np

from rllock.config import GuideConfig
from rllock.core.env import State, apply_chunk, initial_state, make_task, sample_accepted
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


def near_the_end(shape: str, pieces: int, left: int, count: int = 8):
    task = make_task(shape, pieces)
    coords, n = task.topology.coords, task.piece_size
    rng = np.random.default_rng(0)
    placed = pieces - 1 - left
    states = []
    for _ in range(count):
        far = np.argsort(np.abs(coords - coords[rng.integers(len(coords))]).sum(axis=1))[::-1]
        labels = np.zeros(len(coords), np.int16)
        ordered = far[: placed * n]  # the farthest voxels were placed first, the last piece next to R
        labels[ordered] = 1 + np.arange(len(ordered)) // n
        states.append(State(labels, placed))
    return task, states


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--guide", default=None, help="default: an untrained guide of the default size")
    parser.add_argument("--repeats", type=int, default=50)
    parser.add_argument("--left", type=int, default=None, help="states with this many pieces left")
    args = parser.parse_args()
    config = GuideConfig()
    guide = (
        load_guide(args.guide)
        if args.guide
        else Guide(config, init_guide(config, jax.random.PRNGKey(0)), "untrained")
    )
    rows = []
    for shape, pieces in SHAPES:
        task, states = (
            children(shape, pieces) if args.left is None else near_the_end(shape, pieces, args.left)
        )
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
