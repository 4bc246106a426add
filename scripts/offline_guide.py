"""A guide network trained offline on the replay snapshots of several `rllock train-guide` runs.

Each run's buffer (`LOGDIR/replay.npz`: encoded states, value targets, sibling groups) is read whole
into one buffer, and a fresh network with the first run's config learns from it with the learner the
runs use (`learner.guide_learner.GuideLearner`, the first run's batch size, learning rate and sibling
loss weight), `--steps` steps, the sampling drawn from `--seed`. The guide is written as a checkpoint of
a guide run (`OUT/checkpoints/STEPS/`: its parameters and the first run's metadata with an "offline"
record), so `rllock solve --guide OUT` and `rllock bench guide --guide OUT` load it. Every 250 steps it
logs how the network orders siblings of held-out nodes (the same judgement as train-guide's log).

    python scripts/offline_guide.py runs/a,runs/b runs/guide-offline --steps 2000 --seed 0
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
from pathlib import Path

import jax
import numpy as np

from learner.guide_learner import GuideBuffer, GuideLearner, judge
from rllock.config import GuideTrainConfig, from_json
from rllock.errors import RLLockError
from rllock.files import checkpoint as ckpt
from rllock.files.orbax_io import write_state
from rllock.search.guide import channels
from rllock.search.guide_checkpoint import read_guide_metadata

log = logging.getLogger("offline_guide")


def pooled(runs: list[str], config: GuideTrainConfig) -> GuideBuffer:
    """One buffer holding every state of the runs' snapshots, each run's nodes numbered apart."""
    snapshots = [np.load(Path(run) / "replay.npz") for run in runs]
    buffer = GuideBuffer(sum(int(s["size"]) for s in snapshots), config.guide.window, channels(config.guide))
    for s in snapshots:
        n = int(s["size"])
        buffer.add(s["window"][:n], s["features"][:n], s["target"][:n], s["group"][:n] - s["group"][:n].min())
    return buffer


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s", force=True)
    logging.getLogger("absl").setLevel(logging.WARNING)  # orbax's lines about its save threads
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", help="train-guide run folders, comma-separated (the first gives the config)")
    p.add_argument("out", help="the folder the guide is written to (replaced)")
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--seed", type=int, default=0, help="the initial weights and the batches")
    args = p.parse_args()
    runs = args.runs.split(",")
    try:
        doc = read_guide_metadata(ckpt.find_step_dir(runs[0]))
    except RLLockError as exc:
        p.exit(2, f"offline_guide: {exc}\n")
    config = from_json(GuideTrainConfig, doc["config"])
    buffer = pooled(runs, config)
    log.info("%d states from %s", buffer.size, ", ".join(runs))
    learner = GuideLearner(
        config.guide, config.guide_learning_rate, jax.random.PRNGKey(args.seed), config.rank_weight
    )
    for i in range(args.steps):
        learner.update(buffer.sample(config.batch_size, seed=args.seed * 1_000_003 + i))
        if (i + 1) % 250 == 0:
            held = judge(learner.guide, config.guide, buffer.nodes(True, 10_000, 0))
            log.info(
                "step %d: held-out siblings %.1f%% by the guide, %.1f%% by the search's order (%d pairs)",
                i + 1, 100 * held["siblings"], 100 * held["search_order"], held["pairs"],
            )  # fmt: skip
    out = Path(args.out)
    target = out / "checkpoints" / str(args.steps)
    shutil.rmtree(out, ignore_errors=True)
    (target / "meta").mkdir(parents=True)
    write_state(target / "state", {"params": learner.guide})
    doc |= {"step": args.steps, "offline": {"runs": runs, "seed": args.seed, "states": buffer.size}}
    (target / "meta" / "metadata").write_text(json.dumps(doc))
    log.info("the guide: %s", target)


if __name__ == "__main__":
    main()
