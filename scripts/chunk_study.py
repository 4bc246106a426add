"""Which of a node's accepted chunks should become its children? An offline check of what a learned
chunk score could add to the remainder's surface (`SearchConfig.remainder`).

In deep mode a node samples a few hundred accepted chunks and keeps `children` (8) of them: those after
which the remaining volume's surface grows least. That choice decided sofa K=19 (docs/benchmarks.md,
"The remainder's surface"). A guide network that only reorders the 8 kept children cannot change it.

`collect OUT.npz --groups G --seed X`: of G nodes 4-16 pieces before the end, reached by the search on
curriculum tasks, those where a rollout from a kept child or from another fails (`_easy`); for each,
the 8 chunks the solver keeps and up to 8 other accepted chunks drawn at random, each with its local
features (`chunk_features`) and labelled by `--rollouts` searches of `--expansions` node expansions
from the child it makes (`solver.rollout_reach`).
`judge A.npz [B.npz ...]`: on sibling pairs with different labels, how often each single feature and a
pairwise logistic fit of all of them (trained on the other folds of nodes) orders them as the labels
do; and the mean label of the 8 chunks each score would keep.
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np
from guide_siblings import mid_node

from learner.guide_learner import sibling_order
from rllock.config import GuideTrainConfig
from rllock.core import compiled_sampler as sampler
from rllock.core.env import State, Task, apply_chunk, sample_accepted
from rllock.search.base import derive_seed
from rllock.search.solver import SearchConfig, rollout_reach

log = logging.getLogger("chunk_study")

FEATURES = (
    "cut",  # faces to the rest of R
    "placed",  # faces to placed pieces
    "outside",  # faces to the outside of the shape
    "thin",  # R voxels next to the chunk left with 2 or fewer R neighbours, less those before
    "ends",  # the same with 1 or fewer
    "continuations",  # the child's accepted chunks (the lookahead's count)
)


def chunk_features(
    task: Task, state: State, chunk: np.ndarray, child: State, config: SearchConfig
) -> list[float]:
    """FEATURES of the child that `chunk` makes: local to the chunk and its neighbours."""
    nbr = task.topology.arrays[0]
    labels = state.labels
    inside = set(int(v) for v in chunk)
    cut = placed = outside = 0
    around: set[int] = set()
    for v in chunk:
        for u in nbr[v]:
            if u < 0:
                outside += 1
            elif labels[u] != 0:
                placed += 1
            elif int(u) not in inside:
                cut += 1
                around.add(int(u))

    def degree(u: int, without: set[int]) -> int:
        return sum(1 for w in nbr[u] if w >= 0 and labels[w] == 0 and int(w) not in without)

    before = [degree(u, set()) for u in around]
    after = [degree(u, inside) for u in around]
    thin = sum(a <= 2 for a in after) - sum(b <= 2 for b in before)
    ends = sum(a <= 1 for a in after) - sum(b <= 1 for b in before)
    grand = sample_accepted(
        task, child, seed=0, num_samples=config.samples_per_node, closed_share=config.share_for(task),
        thin=1, wide_seeds=True,
    )  # fmt: skip
    continuations = len(sampler.distinct_rows(grand)) if len(grand) else 0
    return [cut, placed, outside, thin, ends, continuations]


def collect(out: str, groups: int, seed: int, rollouts: int, expansions: int) -> None:
    config, search_config = GuideTrainConfig(max_voxels=1000, max_pieces=80), SearchConfig()
    rows: dict[str, list] = {"features": [], "won": [], "reach": [], "kept": [], "group": [], "path": []}
    started = time.monotonic()
    for g in range(groups):
        node = mid_node(seed, g, config)
        if node is None:
            continue
        task, left, state, rng = node
        accepted = sample_accepted(
            task, state, seed=derive_seed(seed, g), num_samples=search_config.samples_per_node,
            closed_share=search_config.share_for(task), thin=1, wide_seeds=True,
        )  # fmt: skip
        if not len(accepted):
            continue
        unique = sampler.distinct_rows(accepted)
        surface = int(search_config.surface(task))
        growth = sampler.remainder_growth(task.topology.arrays[0], state.labels, unique, surface)
        order = np.lexsort((rng.random(len(unique)), growth))
        kept = order[: search_config.children]
        rest = order[search_config.children :]
        others = rng.permutation(rest)[: search_config.children]
        picked = np.r_[kept, others]
        if len(picked) < 4 or _easy(task, state, unique[picked[[0, -1]]], derive_seed(seed, g), expansions):
            continue
        labels = []
        for i, c in enumerate(picked):
            child = apply_chunk(state, unique[c])
            reach = [
                rollout_reach(task, child, seed=derive_seed(seed, g, i, r), expansions=expansions)
                for r in range(rollouts)
            ]
            rows["features"].append(chunk_features(task, state, unique[c], child, search_config))
            rows["reach"].append(reach)
            rows["won"].append(float(np.mean([r == 1.0 for r in reach])))
            rows["kept"].append(i < len(kept))
            rows["group"].append(seed * 10_000 + g)
            rows["path"].append(task.removal == "path")
            labels.append(rows["won"][-1])
        log.info(
            "%d (%.0f s) %s K=%d %s, %d left, %d distinct: kept %s others %s", g, time.monotonic() - started,
            task.shape_name, task.pieces, task.removal, left, len(unique),
            np.round(labels[: len(kept)], 2).tolist(), np.round(labels[len(kept) :], 2).tolist(),
        )  # fmt: skip
        np.savez_compressed(out, **{k: np.asarray(v) for k, v in rows.items()})


def _easy(task: Task, state: State, chunks: np.ndarray, seed: int, expansions: int) -> bool:
    """Whether one rollout from each of two of the node's children (a kept one and another) wins: then
    most likely every child does, and the node tells siblings nothing (most curriculum nodes are so)."""
    return all(
        rollout_reach(task, apply_chunk(state, c), seed=seed + i, expansions=expansions) == 1.0
        for i, c in enumerate(chunks)
    )


def _pairs(x: np.ndarray, t: np.ndarray, group: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Feature differences of sibling pairs with different targets, and 1 where the first is better."""
    dx, y = [], []
    for g in np.unique(group):
        xs, ts = x[group == g], t[group == g]
        i, j = np.triu_indices(len(ts), 1)
        keep = ts[i] != ts[j]
        dx.append(xs[i[keep]] - xs[j[keep]])
        y.append((ts[i[keep]] > ts[j[keep]]).astype(np.float64))
    return np.concatenate(dx), np.concatenate(y)


def fit_pairwise(x: np.ndarray, t: np.ndarray, group: np.ndarray, steps: int = 2000) -> np.ndarray:
    """Weights w of a pairwise logistic model P(i better than j) = sigmoid(w . (x_i - x_j)), by
    gradient descent with a little L2."""
    dx, y = _pairs(x, t, group)
    w = np.zeros(x.shape[1])
    if not len(y):
        return w
    for _ in range(steps):
        p = 1 / (1 + np.exp(-(dx @ w)))
        w -= 0.5 * (dx.T @ (p - y) / len(y) + 1e-3 * w)
    return w


def judge(paths: list[str]) -> None:
    data = [np.load(p) for p in paths]
    x = np.concatenate([d["features"] for d in data]).astype(np.float64)
    won = np.concatenate([d["won"] for d in data])
    reach = np.concatenate([d["reach"] for d in data]).mean(axis=1)
    kept = np.concatenate([d["kept"] for d in data])
    group = np.concatenate([d["group"] for d in data])
    scale = x.std(axis=0) + 1e-9
    xs = x / scale
    nodes = np.unique(group)
    print(f"{len(nodes)} nodes, {len(won)} chunks ({kept.sum()} kept by the solver); mean label kept "
          f"{won[kept].mean():.3f}, others {won[~kept].mean():.3f}")  # fmt: skip
    path = np.concatenate([d["path"] for d in data])
    surface = -(x[:, 0] - x[:, 1] - x[:, 2])
    singles = {f"-{name}": -x[:, i] for i, name in enumerate(FEATURES)}
    singles["-surface growth"] = surface
    singles["the solver's (surface, path: cut)"] = np.where(path, -x[:, 0], surface)
    singles["continuations"] = x[:, 5]
    fold = np.searchsorted(nodes, group) % 5
    local = [FEATURES.index(f) for f in FEATURES if f != "continuations"]
    for name, columns in (
        ("learned, local features", local),
        ("learned, with continuations", list(range(6))),
    ):
        learned = np.zeros(len(won))
        for k in range(5):
            w = fit_pairwise(xs[fold != k][:, columns], reach[fold != k], group[fold != k])
            learned[fold == k] = xs[fold == k][:, columns] @ w
        w_all = fit_pairwise(xs[:, columns], reach, group)
        print(f"weights of {name} (all nodes, per std):",
              dict(zip([FEATURES[c] for c in columns], np.round(w_all, 3).tolist())))  # fmt: skip
        singles[f"{name} (held-out folds)"] = learned
    print(
        "| score | pairs by won, right | pairs by reach, right | mean won of its top 8 "
        "| among the kept only (won) |"
    )
    print("|---|---|---|---|---|")
    for name, s in singles.items():
        a, n = sibling_order(s, won, group, 0.0)
        b, m = sibling_order(s, reach, group, 0.0)
        top = []
        for g in nodes:
            idx = np.flatnonzero(group == g)
            top.append(won[idx[np.argsort(-s[idx], kind="stable")[:8]]].mean())
        c, q = sibling_order(s[kept], won[kept], group[kept], 0.0)
        print(f"| {name} | {a:.1%} of {n} | {b:.1%} of {m} | {np.mean(top):.3f} | {c:.1%} of {q} |")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)
    c = sub.add_parser("collect")
    c.add_argument("out")
    c.add_argument("--groups", type=int, default=100)
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--rollouts", type=int, default=3)
    c.add_argument("--expansions", type=int, default=512)
    j = sub.add_parser("judge")
    j.add_argument("paths", nargs="+")
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", force=True)
    if args.command == "collect":
        collect(args.out, args.groups, args.seed, args.rollouts, args.expansions)
    else:
        judge(args.paths)


if __name__ == "__main__":
    main()
