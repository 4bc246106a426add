"""Does the paper's U-Net policy order the search solver's children well? (issue 33, an experiment)

The paper's MCTS with a trained U-Net found sofa K=19 assemblies (`sofa-k19`, and `general` zero-shot
found sofa K=16) where the search solver finds none: its policy scores a candidate chunk by the mean of
its voxels' logits. Here the same score orders the solver's children (one network call on the parent
per node, the lookahead's dead ends still dropped, nothing pruned), against the plain solver, same seeds:

    python scripts/policy_order.py sofa 19 --checkpoint general --seeds 0,1,2 --time-limit 60
    python scripts/policy_order.py sofa 19 --plain --seeds 0,1,2 --time-limit 60

Prints, per seed, the seconds to the first assembly or the most pieces placed, and the network's share
of the time.
"""

from __future__ import annotations

import argparse
import logging
import time
from dataclasses import dataclass, replace

import jax
import numpy as np

from rllock.core.env import State, Task, make_task
from rllock.search.inference import load_network
from rllock.search.network import PolicyValueNet, canvas_index, encode_batch, fit_canvas
from rllock.search.solver import SearchConfig, SearchStats, search

log = logging.getLogger("policy_order")


@dataclass
class PolicyOrder:
    """Quacks like `rllock.search.guide.Guide` for the solver: `values` of a node's children are the
    sigmoid of the U-Net policy's chunk logit on their parent (the mean logit of the chunk's voxels)."""

    canvas: int
    task_planes: bool
    apply: object
    where: np.ndarray  # each shape voxel's canvas index (`canvas_index`)
    horizon: int = 1 << 30
    seconds: float = 0.0

    def values(self, task: Task, states: list[State], shares: list[float]) -> np.ndarray:
        del shares
        piece = states[0].placed
        parent = states[0].labels.copy()
        parent[parent == piece] = 0
        start = time.perf_counter()
        planes = encode_batch(task, parent[None], np.array([piece - 1]), self.canvas, self.task_planes)
        logits = np.asarray(self.apply(planes)[0])[0]  # type: ignore[operator]
        self.seconds += time.perf_counter() - start
        scores = np.array([logits[self.where[s.labels == piece]].mean() for s in states])
        return 1 / (1 + np.exp(-scores))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("shape")
    p.add_argument("pieces", type=int)
    p.add_argument("--checkpoint", default="general")
    p.add_argument("--plain", action="store_true", help="the solver without the policy")
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--time-limit", type=float, default=60.0)
    p.add_argument("--removal", default="straight")
    args = p.parse_args()
    task = make_task(args.shape, args.pieces, removal=args.removal)
    guide = None
    if not args.plain:
        _, net, params = load_network(args.checkpoint)
        net = fit_canvas(task, replace(net, canvas=None))  # the smallest canvas that fits
        model = PolicyValueNet(net)
        apply = jax.jit(lambda x: model.apply({"params": params}, x))
        guide = PolicyOrder(net.canvas_side(), net.task_planes, apply, canvas_index(task, net.canvas_side()))
    config = SearchConfig(guide_count_weight=0.0, prune_below=0.0)
    for seed in (int(s) for s in args.seeds.split(",")):
        stats = SearchStats()
        start = time.perf_counter()
        found = next(
            search(task, seed=seed, time_limit=args.time_limit, stats=stats, guide=guide, config=config), None
        )  # type: ignore[arg-type]
        seconds = time.perf_counter() - start
        net_seconds = 0.0 if guide is None else guide.seconds
        log.info(
            "%s K=%d %s seed %d: %s, %d expansions, network %.1f s",
            args.shape,
            args.pieces,
            "plain" if guide is None else args.checkpoint,
            seed,
            f"{seconds:.1f} s" if found else f"none ({stats.placed} of {args.pieces - 1})",
            stats.expansions,
            net_seconds,
        )
        if guide is not None:
            guide.seconds = 0.0


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s", force=True)  # an import set a root handler
    main()
