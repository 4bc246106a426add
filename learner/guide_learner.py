"""The guide network's replay buffer and learner (`rllock train-guide`).

The buffer holds encoded search states (`rllock.search.guide.encode`: a window and features, both of a
fixed size whatever the shape) with their value targets and sibling group (the children of one node), in
a ring. The learner minimises, with Adam, the binary cross-entropy between the network's value and the
target (`rllock.actors.guide_actor`: what the rollouts from the state reached) plus `rank_weight` times a
sibling loss: for pairs of children of one node with different targets, the cross-entropy of the
difference of their logits against which target is higher. The search uses the guide to order siblings,
and the value loss alone learns mostly how deep a node is, which does not tell siblings apart. Its step
is a pure jitted function.

One node in `HOLDOUT` (its children together) is never trained on: `judge` measures on those how often
the network orders siblings rightly, against the same on nodes it trains on and against the lookahead
share alone, so that a run shows in TensorBoard whether it learns what carries over or memorises its
own buffer.
"""

from __future__ import annotations

import os
import zipfile
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

from rllock.config import GuideConfig
from rllock.errors import RLLockError
from rllock.learner.learner import AdamState
from rllock.process import peak_rss_mb
from rllock.search.base import BufferCounts
from rllock.search.guide import CHANNELS, GLOBALS, PAD, GuideNet, guide_values, init_guide

HOLDOUT = 10  # one node in this many is held out of training (by its number in the run)
SHARE = GLOBALS - 1  # the feature that is the lookahead share (`rllock.search.guide._features`)


def held_out(group: np.ndarray) -> np.ndarray:
    return group % HOLDOUT == 0


class GuideBuffer:
    """Encoded states, targets and sibling groups; the oldest are overwritten once `capacity` is
    reached. A batch (`sample`) is pairs: its first half drawn uniformly among the states of nodes that
    are not held out (`held_out`), its second half a sibling of each (`paired` says which pairs are
    siblings: a state whose siblings are all gone has none)."""

    def __init__(self, capacity: int, window: int, channels: int = CHANNELS):
        self.capacity = capacity
        self.window = np.zeros((capacity, window, window, window, channels), np.int8)
        self.features = np.zeros((capacity, GLOBALS), np.float32)
        self.target = np.zeros(capacity, np.float32)
        self.group = np.full(capacity, -1, np.int64)
        self.size = self.cursor = self.added = self.received_bytes = self.groups = 0

    def add(
        self, window: np.ndarray, features: np.ndarray, target: np.ndarray, group: np.ndarray
    ) -> BufferCounts:
        """Add a search's states, `group` numbering their nodes from 0 (siblings share a number); returns
        the counts after it."""
        for i in range(len(target)):
            at = self.cursor
            self.window[at], self.features[at], self.target[at] = window[i], features[i], target[i]
            self.group[at] = self.groups + group[i]
            self.cursor = (at + 1) % self.capacity
            self.size = min(self.size + 1, self.capacity)
            self.added += 1
        self.groups += int(group.max()) + 1 if len(group) else 0
        self.received_bytes += window.nbytes + features.nbytes + target.nbytes + group.nbytes
        return self.counts()

    def sample(self, batch: int, seed: int) -> dict[str, np.ndarray]:
        """`batch` states (an even number): `batch // 2` uniform ones, then a random sibling of each."""
        rng = np.random.default_rng(seed)
        group = self.group[: self.size]
        first = rng.choice(np.flatnonzero(~held_out(group)), size=batch // 2)
        second, paired = siblings(group, first, rng)
        idx = np.concatenate([first, second])
        return {
            "window": self.window[idx],
            "features": self.features[idx],
            "target": self.target[idx],
            "paired": paired,
        }

    def nodes(self, held: bool, most: int, seed: int) -> dict[str, np.ndarray]:
        """The states of at most `most` nodes, held out or trained on, drawn at random, siblings
        together; "order" says when each came (the actors push a node's children in the search's pop
        order, best last)."""
        group = self.group[: self.size]
        chosen = np.unique(group[held_out(group) == held])
        chosen = np.random.default_rng(seed).permutation(chosen)[:most]
        idx = np.flatnonzero(np.isin(group, chosen))
        return {
            "window": self.window[idx],
            "features": self.features[idx],
            "target": self.target[idx],
            "group": group[idx],
            # Oldest first: once the ring is full, its oldest state is at the cursor.
            "order": (idx - self.cursor) % self.capacity if self.size == self.capacity else idx,
        }

    def counts(self) -> BufferCounts:
        solved = int((self.target[: self.size] >= 1.0).sum())
        return BufferCounts(self.size, self.added, solved, self.received_bytes, peak_rss_mb())

    def snapshot(self, path: str) -> None:
        """Write the buffer to `path` atomically (a temporary file renamed over it)."""
        state = {name: getattr(self, name)[: self.size] for name in ARRAYS}
        write_snapshot(path, state | {"cursor": self.cursor, "added": self.added, "groups": self.groups})

    def restore(self, path: str) -> int:
        snapshot = read_snapshot(path)
        size = len(snapshot["target"])
        if size > self.capacity or snapshot["window"].shape[1:] != self.window.shape[1:]:
            raise RLLockError(
                f"replay snapshot {path} holds {size} states of window {snapshot['window'].shape[1]}: "
                f"resume with the --buffer-capacity and --window it was made with"
            )
        for name in ARRAYS:
            getattr(self, name)[:size] = snapshot[name]
        self.groups, self.size, self.added = snapshot["groups"], size, snapshot["added"]
        self.cursor = snapshot["cursor"] % self.capacity
        return size


ARRAYS = ("window", "features", "target", "group")  # a snapshot's per-state arrays


def write_snapshot(path: str | Path, snapshot: dict, compressed: bool = False) -> None:
    """Write a snapshot (`read_snapshot`'s form: the arrays and "cursor", "added", "groups") to `path`
    atomically (a temporary file renamed over it); `compressed` for one kept in the repository."""
    tmp = Path(path).with_suffix(".tmp.npz")
    save = np.savez_compressed if compressed else np.savez
    counts = {name: snapshot[name] for name in ("cursor", "added", "groups")}
    save(tmp, size=len(snapshot["target"]), **counts, **{name: snapshot[name] for name in ARRAYS})
    os.replace(tmp, path)


def read_snapshot(path: str | Path) -> dict:
    """A replay snapshot (`GuideBuffer.snapshot`): its states' arrays and the ring's counters. A snapshot
    from before sibling groups gives each state its own group (no pairs among them)."""
    try:
        with np.load(path) as data:
            size = int(data["size"])
            snapshot = {name: data[name][:size] for name in ("window", "features", "target")}
            snapshot["group"] = data["group"][:size] if "group" in data.files else np.arange(size)
            snapshot["groups"] = int(data["groups"]) if "groups" in data.files else size
            snapshot["added"], snapshot["cursor"] = int(data["added"]), int(data["cursor"])
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise RLLockError(f"replay snapshot {path} is missing or damaged: {exc}") from None
    if any(len(snapshot[name]) != size for name in ARRAYS):
        raise RLLockError(f"replay snapshot {path} is damaged: it holds fewer states than it says ({size})")
    return snapshot


def pool(snapshots: dict[str, dict], window: int, channels: int = CHANNELS) -> GuideBuffer:
    """One buffer holding every state of several runs' snapshots (`read_snapshot`, by source), each
    snapshot's sibling groups numbered apart from the others'."""
    total = sum(len(s["target"]) for s in snapshots.values())
    if not total:
        raise RLLockError(f"no states to train on in {', '.join(snapshots)}")
    buffer = GuideBuffer(total, window, channels)
    for source, s in snapshots.items():
        if s["window"].shape[1:] != buffer.window.shape[1:]:
            raise RLLockError(
                f"replay snapshot {source} holds states of window {s['window'].shape[1]} with "
                f"{s['window'].shape[-1]} channels: train on it with the --window and --overview it was "
                f"made with (here {window} and {channels})"
            )
        if len(s["target"]):
            buffer.add(s["window"], s["features"], s["target"], s["group"] - s["group"].min())
    return buffer


# A node has at most `SearchConfig.children` (8) children, stored one after another: a sibling of a state
# lies within this many places of it in the ring.
SIBLINGS_WITHIN = 8


def siblings(group: np.ndarray, first: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """For each index of `first` into `group` (a ring's sibling groups), a random other index of its
    group (itself where it has none) and whether it has one."""
    offsets = np.arange(-SIBLINGS_WITHIN + 1, SIBLINGS_WITHIN)
    near = first[:, None] + offsets[None, :]
    near_ok = (near >= 0) & (near < len(group)) & (offsets[None, :] != 0)
    near = np.where(near_ok, near, 0)
    same = near_ok & (group[near] == group[first][:, None])
    pick = np.argmax(np.where(same, rng.random(same.shape), -1.0), axis=1)
    paired = same.any(axis=1)
    return np.where(paired, near[np.arange(len(first)), pick], first), paired


def sibling_order(
    score: np.ndarray, target: np.ndarray, group: np.ndarray, gap: float = 0.0
) -> tuple[float, int]:
    """(the share of sibling pairs whose targets differ by more than `gap` that `score` orders as the
    targets are ordered, ties counting a half; how many such pairs). Siblings sorted together are
    compared at each offset in turn: time and memory grow with the states times the largest group."""
    order = np.argsort(group, kind="stable")
    g, s, t = group[order], score[order], target[order]
    right, pairs = 0.0, 0
    for k in range(1, len(g)):
        same = g[k:] == g[:-k]
        if not same.any():  # groups are contiguous once sorted: none farther apart either
            break
        dt = t[k:] - t[:-k]
        apart = same & (np.abs(dt) > gap)
        d = (s[k:] - s[:-k])[apart] * dt[apart]
        right += float((d > 0).sum() + 0.5 * (d == 0).sum())
        pairs += int(apart.sum())
    return (right / pairs if pairs else 0.5), pairs


JUDGE_BATCH = 32 * PAD  # states per network call in `encoded_values`: one batch shape, one compile


def encoded_values(params: dict, config: GuideConfig, window: np.ndarray, features: np.ndarray) -> np.ndarray:
    """The network's values of encoded states (a buffer's `window` and `features`), JUDGE_BATCH at a
    time, the last batch padded."""
    n = len(features)
    values = np.zeros(n, np.float32)
    for at in range(0, n, JUDGE_BATCH):
        m = min(JUDGE_BATCH, n - at)
        w = np.zeros((JUDGE_BATCH, *window.shape[1:]), np.int8)
        f = np.zeros((JUDGE_BATCH, GLOBALS), np.float32)
        w[:m], f[:m] = window[at : at + m], features[at : at + m]
        values[at : at + m] = np.asarray(guide_values(params, w, f, config=config))[:m]
    return values


def judge(params: dict, config: GuideConfig, nodes: dict[str, np.ndarray]) -> dict[str, float]:
    """On `GuideBuffer.nodes`: the share of sibling pairs the network's value orders rightly
    ("siblings"), the same for the lookahead share alone ("share") and for the search's own order
    ("search_order": what the guide must beat to be worth its cost), how many pairs ("pairs"), and the
    mean absolute error of the value against the target ("value_error")."""
    n = len(nodes["target"])
    values = encoded_values(params, config, nodes["window"], nodes["features"])
    target, group = nodes["target"], nodes["group"]
    siblings_right, pairs = sibling_order(values, target, group)
    share_right, _ = sibling_order(nodes["features"][:, SHARE], target, group)
    order_right, _ = sibling_order(nodes["order"].astype(np.float64), target, group)
    error = float(np.abs(values - target).mean()) if n else 0.0
    return {
        "siblings": siblings_right,
        "share": share_right,
        "search_order": order_right,
        "pairs": float(pairs),
        "value_error": error,
    }


def guide_losses(params, config: GuideConfig, window, features, target, paired):
    """(value loss, sibling loss) of a batch from `GuideBuffer.sample`: the cross-entropy of each value
    against its target, and over the pairs of siblings with different targets, the cross-entropy of the
    difference of their logits against which is higher (0 without such a pair)."""
    logits: jax.Array = GuideNet(config).apply({"params": params}, window, features)  # type: ignore[assignment]
    value = optax.sigmoid_binary_cross_entropy(logits, target).mean()
    half = target.shape[0] // 2
    apart = paired & (target[:half] != target[half:])
    higher = (target[:half] > target[half:]).astype(jnp.float32)
    rank = optax.sigmoid_binary_cross_entropy(logits[:half] - logits[half:], higher)
    return value, jnp.sum(jnp.where(apart, rank, 0.0)) / jnp.maximum(apart.sum(), 1)


def guide_loss(params, config: GuideConfig, rank_weight: float, window, features, target, paired):
    value, rank = guide_losses(params, config, window, features, target, paired)
    return value + rank_weight * rank, (value, rank)


@partial(jax.jit, static_argnames=("config", "optimizer"))
def guide_step(
    params, opt_state, batch, rank_weight, *, config: GuideConfig, optimizer: optax.GradientTransformation
):
    """One Adam step on `batch` (window, features, target, paired); returns (params, opt_state, (value
    loss, sibling loss))."""
    (_, losses), grads = jax.value_and_grad(guide_loss, has_aux=True)(params, config, rank_weight, *batch)
    updates, opt_state = optimizer.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state, losses


@jax.jit
def moving_average(average, params, decay):
    """One step of an exponential moving average of the weights: decay * average + (1 - decay) * params."""
    return jax.tree.map(lambda a, p: decay * a + (1.0 - decay) * p, average, params)


class GuideLearner(AdamState):
    """The guide network's learner: its parameters, optimizer state, step and PRNG key (`AdamState`),
    and with `weight_average` > 0 a moving average of its parameters, which is the guide (`guide`)."""

    def __init__(
        self,
        config: GuideConfig,
        learning_rate: float,
        key: jax.Array,
        rank_weight: float = 0.0,
        weight_average: float = 0.0,
    ):
        super().__init__(partial(init_guide, config), learning_rate, key)
        self.config, self.rank_weight, self.weight_average = config, rank_weight, weight_average
        self.average = self.params

    @property
    def guide(self) -> dict:
        """The weights the actors search with and checkpoints keep as the guide."""
        return self.average if self.weight_average else self.params

    @property
    def weights(self) -> dict:
        return self.guide

    def state(self) -> dict:
        """As `AdamState.state`, with "params" the guide (what `load_guide` reads) and, when averaging,
        the learner's own parameters under "learner_params"."""
        state = super().state()
        if self.weight_average:
            state |= {"params": self.average, "learner_params": self.params}
        return state

    def load_state(self, state: dict) -> None:
        super().load_state(state)
        if self.weight_average:
            self.average, self.params = state["params"], state["learner_params"]
        else:
            self.average = self.params

    def update(self, sample: dict[str, np.ndarray]) -> tuple[float, float]:
        """One step on a `GuideBuffer.sample`; returns its (value loss, sibling loss)."""
        batch = (
            jnp.asarray(sample["window"], jnp.float32),
            jnp.asarray(sample["features"]),
            jnp.asarray(sample["target"]),
            jnp.asarray(sample["paired"]),
        )
        self.params, self.opt_state, (value, rank) = guide_step(
            self.params, self.opt_state, batch, self.rank_weight, config=self.config, optimizer=self.optimizer
        )
        if self.weight_average:
            self.average = moving_average(self.average, self.params, self.weight_average)
        self.step += 1
        return float(value), float(rank)

    def learn(self, sample: dict[str, np.ndarray]) -> dict[str, float]:
        """One step (`update`); returns its losses by TensorBoard tag."""
        value, rank = self.update(sample)
        return {"losses/value": value, "losses/siblings": rank}
