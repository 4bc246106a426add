"""Whether a guide's value picks better places to restart from (`SearchConfig.dives`).

python scripts/dive_choice.py trials mario:58 runs/guide-mario --seed 3 --trials 300 --dives 16
    each trial: DIVES dives to the guide's horizon, then one restart (BUDGET expansions) from the
    best-valued dive state and one from a dive state drawn at random; how deep each went
python scripts/dive_choice.py rate mario:58 runs/guide-mario --seed 0 --seconds 100 --dives 4
    assemblies found in SECONDS by the solver, and by restarts from dives chosen by the trained and by
    the untrained guide (`search` with `dives`, the search's own order of children), one after another
"""

from __future__ import annotations

import argparse
import logging
import time

import jax
import numpy as np

from rllock.core.env import initial_state
from rllock.search.curriculum import parse_named_task
from rllock.search.guide import Guide, init_guide
from rllock.search.guide_checkpoint import load_guide
from rllock.search.solver import SearchConfig, SearchStats, _dfs, search

log = logging.getLogger("dive_choice")


def trials(args: argparse.Namespace) -> None:
    task, guide = parse_named_task(args.cell).task(), load_guide(args.guide)
    config, target = SearchConfig(), task.pieces - 1
    depth = target - guide.horizon
    best_deep, random_deep = [], []
    for trial in range(args.trials):
        rng = np.random.default_rng([args.seed, trial])
        reached = []
        for _ in range(args.dives):
            state, _ = _dfs(task, rng, config, 100_000, time.monotonic() + 60, depth, SearchStats())
            reached += [] if state is None else [state]
        values = guide.values(task, reached, [1.0] * len(reached))
        deepest = []
        for pick in (int(np.argmax(values)), int(rng.integers(len(reached)))):
            stats = SearchStats()
            bottom = np.random.default_rng([args.seed, trial, 9])
            end, _ = _dfs(
                task, bottom, config, args.budget, time.monotonic() + 600, target, stats, start=reached[pick]
            )
            deepest.append(target if end is not None else stats.placed)
        best_deep.append(deepest[0])
        random_deep.append(deepest[1])
        log.info("trial %d: best-valued -> %d, random -> %d of %d", trial, *deepest, target)
    b, r = np.array(best_deep), np.array(random_deep)
    log.info(
        "%d trials: solved %d (best-valued) against %d (random); deepest on average %.2f against %.2f; "
        "reached %d or more %d against %d times; best deeper in %d, random deeper in %d",
        len(b), (b == target).sum(), (r == target).sum(), b.mean(), r.mean(), target - 1,
        (b >= target - 1).sum(), (r >= target - 1).sum(), (b > r).sum(), (b < r).sum(),
    )  # fmt: skip


def rate(args: argparse.Namespace) -> None:
    task, trained = parse_named_task(args.cell).task(), load_guide(args.guide)
    untrained = Guide(
        trained.config, init_guide(trained.config, jax.random.PRNGKey(0)), "untrained", trained.horizon
    )
    config = SearchConfig(dives=args.dives, dives_from=args.dives_from)
    for g in (trained, untrained):  # compiled before any arm is timed
        g.values(task, [initial_state(task)], [1.0])
    for arm, guide in (("solver", None), ("guided", trained), ("untrained", untrained)):
        stats, began = SearchStats(), time.monotonic()
        arm_config = SearchConfig() if guide is None else config
        found = [
            f.seconds
            for f in search(
                task, seed=args.seed, time_limit=args.seconds, config=arm_config, guide=guide, stats=stats
            )
        ]
        log.info(
            "%s seed %d %s: %d assemblies in %.0f s, %d restarts, %d expansions (%.0f per assembly); first "
            "after %s s",
            args.cell, args.seed, arm, len(found), time.monotonic() - began, stats.restarts, stats.expansions,
            stats.expansions / max(len(found), 1), f"{found[0]:.1f}" if found else "none",
        )  # fmt: skip


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", force=True)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("mode", choices=("trials", "rate"))
    p.add_argument("cell", help="a task as rllock bench guide --cells writes it (mario:58)")
    p.add_argument("guide", help="a train-guide run or checkpoint")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--dives", type=int, default=16)
    p.add_argument("--dives-from", type=int, default=2, help="rate: the first restart that dives")
    p.add_argument("--trials", type=int, default=100)
    p.add_argument("--budget", type=int, default=2000, help="node expansions of each restart (trials)")
    p.add_argument("--seconds", type=float, default=100.0, help="seconds per arm (rate)")
    args = p.parse_args()
    (trials if args.mode == "trials" else rate)(args)


if __name__ == "__main__":
    main()
