"""Can a guide network judge a child better than the solver's own lookahead count? An offline check.

`rollouts OUT.npz --groups G --seed X`: G nodes 4-16 pieces before the end, reached by the plain search
on curriculum tasks, their children as the solver makes them, each labelled by the share of `--rollouts`
plain searches from it that reach an assembly; saved encoded as the guide sees them, with their
lookahead shares and their node.
`fit A.npz [B.npz ...] --steps S [--label reach] [--rank-weight W]`: trains the guide network as
`rllock train-guide` does (`learner.guide_learner`: value loss plus W times the sibling loss) on the
nodes whose index is not a multiple of 5 and, on the others (held out), counts sibling pairs with
different labels ordered rightly by the lookahead share, by the network's value, and by the blend the
guided search uses (value + 0.5 share). The files are `rollouts` files or a `train-guide` run's replay
snapshot (LOGDIR/replay.npz: its targets as that run made them).
`retest A.npz [B.npz ...]`: is a label a property of the remainder or the rollouts' luck? The rollouts
of each child split in two halves, how often one half's label orders sibling pairs as the other's does,
for the share of rollouts that won and for the share of the pieces left they placed
(`solver.rollout_reach`), on every node and on the nodes no rollout won (where the first label is 0).
`judge RUN A.npz [B.npz ...] [--label reach]`: the same counts for a trained guide (a `rllock
train-guide` run or checkpoint) on nodes it never saw, against either label, and how well its best
child's value says a node is lost (no rollout of any child won), the decision
`SearchConfig.abandon_below` makes.

(Until b6b005b a `collect` command recorded the search's own targets, the share of the pieces left
that the DFS below a state placed; docs/benchmarks.md has what `fit` made of them.)
"""

import argparse
import dataclasses
import logging
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

from actors.guide_actor import label_children
from learner.guide_learner import guide_step, sibling_order, siblings
from rllock.config import GuideConfig, GuideTrainConfig
from rllock.core.env import State, Task
from rllock.search.curriculum import draw_task
from rllock.search.guide import guide_values, init_guide
from rllock.search.solver import reach_depth

log = logging.getLogger("guide_siblings")


def _append(rows: dict[str, list], **values) -> None:
    for key, value in values.items():
        rows[key].append(value)


def mid_node(
    seed: int, number: int, config: GuideTrainConfig
) -> tuple[Task, int, State, np.random.Generator] | None:
    """Node `number` of a study seeded `seed`: a curriculum task of K >= 8, how many pieces are left
    (4-16), a state the plain search reached with that many left, and the generator that drew them (for
    the study's further draws); or None (K too small, no state within 5 s)."""
    rng = np.random.default_rng([seed, number])
    task = draw_task(rng, config)
    if task.pieces < 8:
        return None
    left = int(rng.integers(4, min(16, task.pieces - 2) + 1))
    state = reach_depth(task, task.pieces - 1 - left, seed=number, time_limit=5)
    return None if state is None else (task, left, state, rng)


def rollouts(out: str, groups: int, rollouts_per: int, expansions: int, seed: int) -> None:
    """Sibling groups labelled by rollouts: a mid-episode state 4-16 pieces before the end, its children
    as the solver makes them (lookahead share included) and labelled as `rllock train-guide` labels them
    (`actors.guide_actor.label_children`: the share of `rollouts_per` plain searches from a child,
    `expansions` each, that reach an assembly)."""
    keys = ("window", "features", "target", "reach", "share", "group", "task")
    rows: dict[str, list] = {k: [] for k in keys}
    config = GuideTrainConfig(max_voxels=600, max_pieces=60)
    labels_config = dataclasses.replace(config, rollouts=rollouts_per, rollout_expansions=expansions)
    for g in range(groups):
        node = mid_node(seed, g, config)
        if node is None:
            continue
        task, left, state, _ = node
        labelled = label_children(task, [state], labels_config, seed=g)
        if len(labelled.target) < 2:
            continue
        # The lookahead share is the guide's last feature (`rllock.search.guide._features`).
        for window, features, target, reach in zip(
            labelled.window, labelled.features, labelled.target, labelled.reach
        ):
            _append(rows, window=window, features=features, target=target, reach=reach, share=features[-1],
                    group=seed * 10_000 + g, task=seed * 10_000 + g)  # fmt: skip
        log.info("%s K=%d %s, %d left: children's rollout labels %s", task.shape_name, task.pieces,
                 task.removal, left, labelled.target.round(2).tolist())  # fmt: skip
        np.savez_compressed(out, **{k: np.asarray(v) for k, v in rows.items()})


def fit(paths: list[str], steps: int, label: str, rank_weight: float, seed: int) -> None:
    data = [np.load(p) for p in paths]
    d = {
        k: np.concatenate([x[k] for x in data])
        for k in data[0].files
        if k not in ("size", "cursor", "added", "groups")
    }
    if "task" not in d:  # a replay snapshot: its nodes are its groups, the share is the last feature
        d["task"], d["share"] = d["group"], d["features"][:, -1]
    elif label == "reach":
        d["target"] = d["reach"].mean(axis=1)
    held = d["task"] % 5 == 0
    log.info("%d states (%d held out), targets: %.0f%% zero, %.0f%% one", len(held), held.sum(),
             100 * (d["target"] == 0).mean(), 100 * (d["target"] == 1).mean())  # fmt: skip
    config = GuideConfig()
    params = init_guide(config, jax.random.key(seed))
    optimizer = optax.adam(1e-3)
    opt_state = optimizer.init(params)
    train = np.flatnonzero(~held)
    rng = np.random.default_rng(seed)
    started = time.monotonic()
    for step in range(1, steps + 1):
        first = rng.choice(train, 128)
        second, paired = siblings(d["group"], first, rng)  # held-out nodes are whole groups: never drawn
        idx = np.concatenate([first, second])
        batch = (jnp.asarray(d["window"][idx], jnp.float32), jnp.asarray(d["features"][idx]),
                 jnp.asarray(d["target"][idx]), jnp.asarray(paired))  # fmt: skip
        params, opt_state, (value, rank) = guide_step(
            params, opt_state, batch, rank_weight, config=config, optimizer=optimizer
        )
        if step % 500 == 0:
            log.info("step %d value loss %.4f sibling loss %.4f (%.0f s)", step, float(value), float(rank),
                     time.monotonic() - started)  # fmt: skip
    test = np.flatnonzero(held)
    chunks = np.array_split(test, max(1, len(test) // 512))
    values = np.concatenate([
        np.asarray(guide_values(params, jnp.asarray(d["window"][c], jnp.float32),
                                jnp.asarray(d["features"][c]), config=config))
        for c in chunks
    ])  # fmt: skip
    target, group, share = d["target"][test], d["group"][test], d["share"][test]
    won = {g for g in np.unique(group) if target[group == g].max() >= 1.0}
    lost = ~np.isin(group, list(won))
    for name, score in (("lookahead share", share), ("network value", values), ("value + 0.5 share",
                        values + 0.5 * share)):  # fmt: skip
        for gap in (0.0, 0.2):
            right, total = sibling_order(score, target, group, gap)
            log.info("held out: %-18s orders %.1f%% of %d sibling pairs (targets apart by more than %.1f)"
                     " rightly", name, 100 * right, total, gap)  # fmt: skip
        right, total = sibling_order(score[lost], target[lost], group[lost], 0.0)
        log.info("held out: %-18s orders %.1f%% of %d sibling pairs on nodes no child of which won",
                 name, 100 * right, total)  # fmt: skip
    log.info("held out: mean |value - target| %.3f (predicting the mean: %.3f)",
             np.abs(values - target).mean(), np.abs(target - d["target"][train].mean()).mean())  # fmt: skip


def retest(paths: list[str]) -> None:
    data = [np.load(p) for p in paths]
    reach = np.concatenate([x["reach"] for x in data])
    group = np.concatenate([x["group"] for x in data])
    half = reach.shape[1] // 2
    a, b = reach[:, :half], reach[:, half : 2 * half]
    nodes = np.unique(group)
    lost = np.isin(group, [g for g in nodes if (reach[group == g] == 1.0).sum() == 0])
    log.info("%d children of %d nodes, %d rollouts each (halves of %d); %d nodes where no rollout won",
             len(group), len(nodes), reach.shape[1], half, len(np.unique(group[lost])))  # fmt: skip
    for name, label in (("won", lambda r: (r == 1.0).mean(axis=1)), ("reach", lambda r: r.mean(axis=1))):
        for where, mask in (("every node", np.ones(len(group), bool)), ("no rollout won", lost)):
            right, total = sibling_order(label(a)[mask], label(b)[mask], group[mask], 0.0)
            log.info("%-5s on %-14s: half A orders %.1f%% of %d sibling pairs half B tells apart as B does",
                     name, where, 100 * right, total)  # fmt: skip


def judge(run: str, paths: list[str], label: str) -> None:
    from rllock.search.guide_checkpoint import load_guide

    guide = load_guide(run)
    data = [np.load(p) for p in paths]
    d = {k: np.concatenate([x[k] for x in data]) for k in data[0].files}
    won = d["target"]
    if label == "reach":  # the children's labels as `train-guide --label reach` makes them
        d["target"] = d["reach"].mean(axis=1)
    values = np.concatenate([
        np.asarray(guide_values(guide.params, jnp.asarray(d["window"][c], jnp.float32),
                                jnp.asarray(d["features"][c]), config=guide.config))
        for c in np.array_split(np.arange(len(d["target"])), max(1, len(d["target"]) // 512))
    ])  # fmt: skip
    target, group, share = d["target"], d["group"], d["share"]
    log.info("%s on %d children of %d nodes: labels mean %.2f, %.0f%% zero; mean |value - label| %.3f "
             "(predicting the mean: %.3f)", guide.source, len(target), len(np.unique(group)), target.mean(),
             100 * (target == 0).mean(), np.abs(values - target).mean(),
             np.abs(target - target.mean()).mean())  # fmt: skip
    for name, score in (("lookahead share", share), ("network value", values), ("value + 0.5 share",
                        values + 0.5 * share)):  # fmt: skip
        right, total = sibling_order(score, target, group, 0.0)
        log.info(
            "%-18s orders %.1f%% of %d sibling pairs with different labels rightly", name, 100 * right, total
        )
    nodes = np.unique(group)
    best = np.array([values[group == g].max() for g in nodes])
    lost = np.array([won[group == g].max() == 0 for g in nodes])
    log.info("%d of %d nodes lost (every child labelled 0)", lost.sum(), len(nodes))
    for below in (0.05, 0.1, 0.2, 0.3, 0.5):
        flagged = best < below
        log.info("best child valued below %.2f: %d nodes, %d of them lost (of %d)", below, flagged.sum(),
                 (flagged & lost).sum(), lost.sum())  # fmt: skip


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("rollouts")
    r.add_argument("out")
    r.add_argument("--groups", type=int, default=100)
    r.add_argument("--rollouts", type=int, default=3)
    r.add_argument("--expansions", type=int, default=512)
    r.add_argument("--seed", type=int, default=0)
    f = sub.add_parser("fit")
    f.add_argument("paths", nargs="+")
    f.add_argument("--steps", type=int, default=3000)
    f.add_argument("--label", choices=("won", "reach"), default="won")
    f.add_argument("--rank-weight", type=float, default=0.0)
    f.add_argument("--seed", type=int, default=0)
    t = sub.add_parser("retest")
    t.add_argument("paths", nargs="+")
    j = sub.add_parser("judge")
    j.add_argument("run")
    j.add_argument("paths", nargs="+")
    j.add_argument("--label", choices=("won", "reach"), default="won")
    args = parser.parse_args()
    if args.cmd == "rollouts":
        rollouts(args.out, args.groups, args.rollouts, args.expansions, args.seed)
    elif args.cmd == "retest":
        retest(args.paths)
    elif args.cmd == "judge":
        judge(args.run, args.paths, args.label)
    else:
        fit(args.paths, args.steps, args.label, args.rank_weight, args.seed)


if __name__ == "__main__":
    main()
