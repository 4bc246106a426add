"""Whether a guide's value picks better places to restart from (`SearchConfig.dives`).

python scripts/dive_choice.py trials mario:58 runs/guide-mario --seed 3 --trials 300 --dives 16
    each trial: DIVES dives to the guide's horizon, then one restart (BUDGET expansions) from the
    best-valued dive state and one from a dive state drawn at random; how deep each went (`--untrained
    --untrained-seed S`: the guide's network at initial weights drawn with S)
python scripts/dive_choice.py rate mario:58 runs/guide-mario --seed 0 --seconds 100 --dives 4
    assemblies found in SECONDS by the solver, and by restarts from dives chosen by the trained and by
    the untrained guide (`search` with `dives`, the search's own order of children), one after another
python scripts/dive_choice.py states mario:60 dives.npz --seed 0 --trials 150 --rollouts 2 --budget 2000
    dive states as the search makes them (`--horizon` pieces before the end; no guide needed), each
    labelled by ROLLOUTS restarts from it of BUDGET expansions (`solver.rollout_reach`)
python scripts/dive_choice.py rank mario:60 dives.npz,more.npz runs/guide-mario runs/guide-mario-b ...
    how each guide (and the untrained network of the first one's config) ranks those states: Spearman
    of value against mean reach, and the rollouts won by the best-valued of GROUP states drawn at random
    (as a restart takes the best of its pool) against the group's mean
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np
from scipy.stats import spearmanr

from rllock.core.env import State, initial_state
from rllock.search.base import derive_seed
from rllock.search.curriculum import parse_named_task
from rllock.search.guide import untrained_like
from rllock.search.guide_checkpoint import load_guide
from rllock.search.solver import SearchConfig, SearchStats, _dfs, rollout_reach, search

log = logging.getLogger("dive_choice")


def trials(args: argparse.Namespace) -> None:
    task, guide = parse_named_task(args.cell).task(), load_guide(args.guide)
    guide = untrained_like(guide, args.untrained_seed) if args.untrained else guide
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
    untrained = untrained_like(trained)
    config = SearchConfig(dives=args.dives, dive_share=args.dive_share)
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


def states(args: argparse.Namespace) -> None:
    task, config = parse_named_task(args.cell).task(), SearchConfig()
    depth = task.pieces - 1 - args.horizon
    budget = 2 * config.restart_unit(task, task.pieces - 1)
    labels, reach = [], []
    for trial in range(args.trials):
        rng = np.random.default_rng([args.seed, trial])
        state, _ = _dfs(task, rng, config, budget, time.monotonic() + 600, depth, SearchStats())
        if state is None:
            continue
        seeds = [derive_seed(args.seed, trial, r) for r in range(args.rollouts)]
        reach.append([rollout_reach(task, state, seed=s, expansions=args.budget) for s in seeds])
        labels.append(state.labels)
        log.info("trial %d: reach %s", trial, " ".join(f"{r:.2f}" for r in reach[-1]))
        # After every state: a run stopped early keeps the minutes of restarts it spent.
        np.savez(args.out, labels=np.asarray(labels), reach=np.asarray(reach), placed=depth)
    won = np.asarray(reach) == 1.0
    log.info(
        "%d dive states; rollouts won %.1f%%, states with a win %d",
        len(reach),
        100 * won.mean(),
        won.any(1).sum(),
    )


def rank(args: argparse.Namespace) -> None:
    task, saved = parse_named_task(args.cell).task(), [np.load(f) for f in args.out.split(",")]
    dives = [State(row.astype(np.int16), int(s["placed"])) for s in saved for row in s["labels"]]
    rollouts = np.concatenate([s["reach"] for s in saved])
    reach, won = rollouts.mean(axis=1), (rollouts == 1.0).mean(axis=1)
    guides = [load_guide(g) for g in args.guides]
    guides.append(untrained_like(guides[0]))
    groups = np.random.default_rng(args.seed).integers(len(dives), size=(args.groups, args.group))
    log.info("%d dive states, mean reach %.3f, rollouts won %.3f", len(dives), reach.mean(), won.mean())
    for guide in guides:
        values = guide.values(task, dives, [1.0] * len(dives))
        best = groups[np.arange(len(groups)), np.argmax(values[groups], axis=1)]
        by_reach, by_won = spearmanr(values, reach).statistic, spearmanr(values, won).statistic
        log.info(
            "%s: Spearman(value, reach) %+.3f, (value, won) %+.3f; best of %d: won %.3f, reach %.3f "
            "(group mean %.3f, %.3f)",
            guide.source, by_reach, by_won, args.group, won[best].mean(), reach[best].mean(),
            won[groups].mean(), reach[groups].mean(),
        )  # fmt: skip


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", force=True)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("mode", choices=("trials", "rate", "states", "rank"))
    p.add_argument("cell", help="a task as rllock bench guide --cells writes it (mario:58)")
    p.add_argument("guide", help="a train-guide run or checkpoint (states, rank: the .npz of the states)")
    p.add_argument("guides", nargs="*", help="rank: the guides (runs or checkpoints) to compare")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--dives", type=int, default=16)
    p.add_argument(
        "--dive-share",
        type=float,
        default=SearchConfig.dive_share,
        help="rate: the diving restarts' share of the solver's",
    )
    p.add_argument("--trials", type=int, default=100)
    p.add_argument("--untrained", action="store_true", help="trials: the initial weights")
    p.add_argument("--untrained-seed", type=int, help="trials, with --untrained: its seed (0)")
    p.add_argument("--budget", type=int, default=2000, help="node expansions of each restart (trials)")
    p.add_argument("--seconds", type=float, default=100.0, help="seconds per arm (rate)")
    p.add_argument("--horizon", type=int, default=20, help="states: pieces left at a dive state")
    p.add_argument("--rollouts", type=int, default=2, help="states: restarts that label a dive state")
    p.add_argument("--groups", type=int, default=10_000, help="rank: random groups of dive states")
    p.add_argument("--group", type=int, default=8, help="rank: dive states a restart chooses among")
    args = p.parse_args()
    if args.untrained_seed is not None and not args.untrained:
        p.error("--untrained-seed draws the untrained network's weights: give it with --untrained")
    args.untrained_seed = args.untrained_seed or 0
    if args.mode in ("states", "rank"):
        args.out = args.guide
    {"trials": trials, "rate": rate, "states": states, "rank": rank}[args.mode](args)


if __name__ == "__main__":
    main()
