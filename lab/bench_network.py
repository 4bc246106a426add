"""Lab study, outside the installed package.
Question: What does one U-Net evaluation cost by canvas side?
Answer: docs/results.md; the measurements: docs/notebook/benchmarks.md,
"Scaling: actors and nodes on one machine".

The U-Net's cost per evaluation by canvas side: `general`'s network (its weights, which fit any side)
on a batch of states, jitted, on this machine's default JAX device; the median of ROUNDS timed calls
after one to compile, and the cost per state relative to the first canvas.

    .venv/bin/python lab/bench_network.py [CANVASES] [BATCH] [ROUNDS]   (default 8,12,16 16 20)
"""

import dataclasses
import statistics
import sys
import time

import jax
import jax.numpy as jnp

from rllock.search.inference import load_network
from rllock.search.network import PolicyValueNet, planes_of

canvases = [int(c) for c in (sys.argv[1] if len(sys.argv) > 1 else "8,12,16").split(",")]
batch = int(sys.argv[2]) if len(sys.argv) > 2 else 16
rounds = int(sys.argv[3]) if len(sys.argv) > 3 else 20
_, net, params = load_network("general")
device = jax.devices()[0].platform
print(f"general's U-Net (features {net.features}), batch {batch}, {device}, median of {rounds}")
base = None
for canvas in canvases:
    config = dataclasses.replace(net, canvas=canvas)
    apply = jax.jit(lambda p, x, config=config: PolicyValueNet(config).apply({"params": p}, x))
    planes = jnp.zeros((batch, canvas, canvas, canvas, planes_of(config)), jnp.float32).at[..., 0].set(1.0)
    jax.block_until_ready(apply(params, planes))  # compile
    times = []
    for _ in range(rounds):
        start = time.perf_counter()
        jax.block_until_ready(apply(params, planes))
        times.append(time.perf_counter() - start)
    per_state = 1000 * statistics.median(times) / batch
    base = base or per_state
    ratio = per_state / base
    print(f"{canvas}^3 ({canvas**3} voxels): {per_state:.2f} ms per state, x{ratio:.2f} the first canvas")
