"""What a guide run's replay buffer says about its network: sibling pairs ordered rightly by the guide, by
the search's own order (the order an actor pushed a node's children in, best last) and by the lookahead
share, on held-out and trained-on nodes; a pairwise logistic model of the features and the search's order
(5-fold by node); and how well the value ranks whole nodes (Spearman of a node's best label against its
best value).

    python scripts/guide_nodes.py runs/guide-mario
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

from learner.guide_learner import SHARE, encoded_values, held_out, sibling_order
from rllock.search.guide import GLOBALS
from rllock.search.guide_checkpoint import load_guide

log = logging.getLogger("guide_nodes")


def positions(group: np.ndarray) -> np.ndarray:
    """Each state's place among its siblings in buffer order, 0 (tried last) to 1 (tried first)."""
    pos = np.zeros(len(group))
    for g in np.unique(group):
        idx = np.flatnonzero(group == g)
        pos[idx] = np.arange(len(idx)) / max(len(idx) - 1, 1)
    return pos


def fit_logistic(x: np.ndarray, y: np.ndarray, l2: float = 1e-2, steps: int = 2000) -> np.ndarray:
    w = np.zeros(x.shape[1])
    for _ in range(steps):
        p = 1 / (1 + np.exp(-x @ w))
        w -= 0.5 * (x.T @ (p - y) / len(y) + l2 * w)
    return w


def pairwise_cv(x: np.ndarray, target: np.ndarray, group: np.ndarray, folds: int = 5) -> tuple[float, int]:
    """Sibling pairs with different labels ordered rightly by a logistic model of feature differences,
    fitted on the other folds' nodes."""
    a, b = [], []
    for g in np.unique(group):
        idx = np.flatnonzero(group == g)
        for i in idx:
            for j in idx:
                if i < j and target[i] != target[j]:
                    a.append(i)
                    b.append(j)
    ia, ib = np.array(a), np.array(b)
    d, y, g = x[ib] - x[ia], target[ib] > target[ia], group[ia]
    nodes = np.random.default_rng(0).permutation(np.unique(g))
    right = 0
    for part in np.array_split(nodes, folds):
        test = np.isin(g, part)
        w = fit_logistic(np.vstack([d[~test], -d[~test]]), np.r_[y[~test], ~y[~test]].astype(float))
        right += int(((d[test] @ w > 0) == y[test]).sum())
    return right / len(y), len(y)


def rank(x: np.ndarray) -> np.ndarray:
    return np.argsort(np.argsort(x)).astype(float)


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s", force=True)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", type=Path)
    args = p.parse_args()
    data = np.load(args.run / "replay.npz")
    n = int(data["size"])
    group, target = data["group"][:n], data["target"][:n]
    features, window = data["features"][:n], data["window"][:n]
    net = load_guide(args.run)
    pos, values = positions(group), encoded_values(net.params, net.config, window, features)
    for name, mask in (("held out", held_out(group)), ("trained on", ~held_out(group))):
        t, g = target[mask], group[mask]
        guide, pairs = sibling_order(values[mask], t, g)
        own, _ = sibling_order(pos[mask], t, g)
        share, _ = sibling_order(features[mask][:, SHARE], t, g)
        log.info(
            "%s: %d pairs; ordered rightly by the guide %.1f%%, the search's order %.1f%%, the share %.1f%%",
            name, pairs, 100 * guide, 100 * own, 100 * share,
        )  # fmt: skip
        nodes = np.unique(g)
        best_t = np.array([t[g == k].max() for k in nodes])
        best_v = np.array([values[mask][g == k].max() for k in nodes])
        left = np.array([features[mask][g == k][0, 0] for k in nodes])
        top = best_v >= np.quantile(best_v, 0.75)
        log.info(
            "%s: %d nodes; Spearman of the best label with the best value %.2f (with the share of the shape "
            "left %.2f); best label %.2f on average, %.2f in the top quarter by value",
            name, len(nodes), np.corrcoef(rank(best_t), rank(best_v))[0, 1],
            np.corrcoef(rank(best_t), rank(left))[0, 1], best_t.mean(), best_t[top].mean(),
        )  # fmt: skip
    x = np.concatenate([features, pos[:, None]], axis=1)
    x = (x - x.mean(axis=0)) / (x.std(axis=0) + 1e-6)
    for cols, name in (
        (slice(None), "features and order"),
        (slice(0, GLOBALS), "features"),
        (slice(GLOBALS, None), "order"),
    ):
        right, pairs = pairwise_cv(x[:, cols], target, group)
        log.info(
            "a pairwise logistic model of the %s: %.1f%% of %d pairs (5-fold by node)",
            name,
            100 * right,
            pairs,
        )


if __name__ == "__main__":
    main()
