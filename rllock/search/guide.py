"""The guide network: a learned judgement of a search state, at a cost that does not grow with the shape.

The search solver (`rllock.search.solver`) places pieces one at a time; where it fails, the failure is set
pieces before the end by what remains of the shape. The guide gives each child of a node (within its
horizon: the last pieces) a value in [0, 1], the chance that a plain search from it reaches an assembly
(what `rllock train-guide` labels by rollouts), from what it sees of the state:
- a window of W^3 voxels centred on the piece just placed, where the next piece starts (`WINDOW`
  channels: the remaining volume R, the placed pieces, outside the shape);
- features (`GLOBALS`): how much is left of the shape and of the pieces, the piece size, N and K, and
  R's shape in a (2W)^3 box around the window: its thin, surface and interior voxels, its extent; and
  the state's lookahead share (its accepted continuations over the most among its siblings), the
  solver's own judgement, which the network learns to correct.
Every input is read from boxes of a fixed size and a few counts, so one evaluation (features and
network) costs the same at N = 500 and N = 40,000, and one set of weights serves every shape and every
K. All children of a node are evaluated in one call.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from rllock.config import GuideConfig
from rllock.core.env import State, Task
from rllock.search.network import Conv3

CHANNELS = 3  # remaining volume, placed pieces, outside the shape
OVERVIEW = 2  # with `GuideConfig.overview`: R and the placed pieces in R's bounding box, in percent
GLOBALS = 15
PAD = 8  # network calls take a multiple of this many states


def channels(config: GuideConfig) -> int:
    """The window's channels: `CHANNELS`, and the overview's after them when the config has one."""
    return CHANNELS + OVERVIEW * config.overview


class GuideNet(nn.Module):
    """(window [B, W, W, W, channels(config)], globals [B, GLOBALS]) -> value logits [B]."""

    config: GuideConfig

    @nn.compact
    def __call__(self, window: jax.Array, features: jax.Array) -> jax.Array:
        towers = [window[..., :CHANNELS]]
        if self.config.overview:  # another place and scale: convolutions of its own
            towers.append(window[..., CHANNELS:] / 100.0)
        flat = []
        for x in towers:
            for f in self.config.guide_features:
                x = nn.relu(Conv3(f)(x))  # the U-Net's matmul convolution: several times XLA's on the CPU
                x = nn.avg_pool(x, (2, 2, 2), strides=(2, 2, 2))
            flat.append(x.reshape(x.shape[0], -1))
        x = jnp.concatenate([*flat, features], axis=-1)
        x = nn.relu(nn.Dense(self.config.guide_hidden)(x))
        x = nn.relu(nn.Dense(self.config.guide_hidden)(x))
        return nn.Dense(1)(x)[:, 0]


@partial(jax.jit, static_argnums=0)
def init_guide(config: GuideConfig, key: jax.Array) -> dict:
    """Fresh guide parameters, initialised as one compiled program (see `init_params`)."""
    w = config.window
    window = jnp.zeros((1, w, w, w, channels(config)))
    return GuideNet(config).init(key, window, jnp.zeros((1, GLOBALS)))["params"]


@partial(jax.jit, static_argnames=("config",))
def guide_values(params: dict, window: jax.Array, features: jax.Array, *, config: GuideConfig) -> jax.Array:
    """Values in [0, 1] for a batch of encoded states."""
    logits: jax.Array = GuideNet(config).apply({"params": params}, window, features)  # type: ignore[assignment]
    return jax.nn.sigmoid(logits)


@dataclass(frozen=True)
class Encoded:
    """A batch of states as the guide sees them."""

    window: np.ndarray  # int8 [B, W, W, W, channels(config)]
    features: np.ndarray  # float32 [B, GLOBALS]


def encode(task: Task, states: list[State], shares: list[float], config: GuideConfig) -> Encoded:
    """The guide's inputs for `states` of `task` with their lookahead shares (module docstring); each
    state's last placed piece is the window's centre (the root, with none: the shape's centre)."""
    w = config.window
    windows = np.zeros((len(states), w, w, w, channels(config)), np.int8)
    features = np.zeros((len(states), GLOBALS), np.float32)
    for i, state in enumerate(states):
        centre = np.round(_centre(task, state)).astype(np.int64)  # once: both boxes are around it
        windows[i, ..., :CHANNELS] = _window(task, state, centre, w)
        if config.overview:
            windows[i, ..., CHANNELS:] = overview(task, state, w)
        features[i] = _features(task, state, centre, 2 * w, shares[i])
    return Encoded(windows, features)


def overview(task: Task, state: State, w: int) -> np.ndarray:
    """int8 [w, w, w, OVERVIEW]: R's bounding box scaled by the same factor along every axis so that it
    fits w (never enlarged), from its low corner; per cell, the percent of its voxels that are in R and
    that are placed pieces. Finding R is a mask over the labels (linear in N); the rest follows R's box,
    small within the guide's horizon, the last pieces."""
    topo = task.topology
    free = topo.coords[state.labels == 0]
    out = np.zeros((w, w, w, OVERVIEW), np.int8)
    if not len(free):
        return out
    lo, hi = free.min(axis=0), free.max(axis=0) + 1
    step = max(1.0, float((hi - lo).max()) / w)  # box voxels per cell along an axis
    box = topo.index[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
    inside = box >= 0
    label = np.where(inside, state.labels[np.where(inside, box, 0)], -1)
    cell = (np.indices(box.shape).reshape(3, -1).T / step).astype(np.int64)
    flat = np.ravel_multi_index(cell.T, (w, w, w))
    volume = np.bincount(flat, minlength=w**3)
    for c, mask in enumerate((label == 0, label > 0)):
        counts = np.bincount(flat, weights=mask.ravel(), minlength=w**3)
        out[..., c] = np.round(100 * counts / np.maximum(volume, 1)).reshape(w, w, w)
    return out


def _centre(task: Task, state: State) -> np.ndarray:
    """Where the next piece starts: the piece just placed (at the root, the shape's centre)."""
    topo = task.topology
    if state.placed:
        # P_i's voxels are the only ones labelled i; their bounding box's centre is cheap and close.
        last = topo.coords[state.labels == state.placed]
        return (last.min(axis=0) + last.max(axis=0)) / 2
    return (np.array(topo.dims) - 1) / 2


def _remaining_box(task: Task, state: State, lo: np.ndarray, side: int) -> np.ndarray:
    """int8 [side, side, side]: 1 on R, 0 on placed pieces, -1 outside the shape, in the box from `lo`."""
    topo = task.topology
    out = np.full((side, side, side), -1, np.int8)
    dims = np.array(topo.dims)
    a, b = np.maximum(lo, 0), np.minimum(lo + side, dims)
    if (b <= a).any():
        return out
    index = topo.index[a[0] : b[0], a[1] : b[1], a[2] : b[2]]
    inside = index >= 0
    values = np.where(inside, (state.labels[np.where(inside, index, 0)] == 0).astype(np.int8), -1)
    out[tuple(slice(a[i] - lo[i], b[i] - lo[i]) for i in range(3))] = values
    return out


def _window(task: Task, state: State, centre: np.ndarray, w: int) -> np.ndarray:
    box = _remaining_box(task, state, centre - w // 2, w)
    return np.stack([box == 1, box == 0, box == -1], axis=-1).astype(np.int8)


def _features(task: Task, state: State, centre: np.ndarray, side: int, share: float) -> np.ndarray:
    """GLOBALS features: the task and how much is left (O(1)), and R's shape in the box of `side`^3
    around the window's centre (its thin, surface and interior voxels, its extent, its share)."""
    n, k, size = task.piece_size, task.pieces, task.size
    left = k - 1 - state.placed
    r = size - n * state.placed  # P1..Pi hold n voxels each
    lo = centre - side // 2
    box = _remaining_box(task, state, lo - 1, side + 2) == 1
    inner = box[1:-1, 1:-1, 1:-1]
    degree = (
        box[:-2, 1:-1, 1:-1].astype(np.int8)
        + box[2:, 1:-1, 1:-1]
        + box[1:-1, :-2, 1:-1]
        + box[1:-1, 2:, 1:-1]
        + box[1:-1, 1:-1, :-2]
        + box[1:-1, 1:-1, 2:]
    )[inner]
    there = int(inner.sum())
    extent = np.zeros(3)
    if there:
        where = np.argwhere(inner)
        extent = (where.max(axis=0) - where.min(axis=0) + 1) / side
    return np.array(
        [
            r / size,
            left / max(k - 1, 1),
            min(n, 64) / 64,
            np.log(size) / 11,
            np.log(k) / 8,
            float((degree <= 2).mean()) if there else 0.0,  # thin voxels: strands no piece can be cut from
            float((degree <= 4).mean()) if there else 0.0,  # R's surface
            float((degree == 6).mean()) if there else 0.0,  # R's interior
            *extent,
            there / side**3,
            r / max(left, 1) / max(n, 1) / 2,  # voxels left per piece left, against n
            float(state.placed > 0),
            share,
        ],
        np.float64,
    )


@dataclass(frozen=True)
class Guide:
    """A guide network with its weights: `values(task, states)` in one call."""

    config: GuideConfig
    params: dict
    source: str  # a checkpoint's path or name, or "untrained (seed N)"
    horizon: int = 20
    """Dives stop this many pieces before the end (`SearchConfig.dives`): where it was trained
    (`--max-left`)."""

    def values(self, task: Task, states: list[State], shares: list[float]) -> np.ndarray:
        """Values of `states` with their lookahead shares (`dfs.Child`), in one network call padded
        to a multiple of `PAD` states: a node has 1 to 8 children, and each new batch shape would
        compile the network again."""
        if not states:
            return np.zeros(0, np.float32)
        e = encode(task, states, shares, self.config)
        rows = -(-len(states) // PAD) * PAD
        window = np.zeros((rows, *e.window.shape[1:]), np.int8)
        features = np.zeros((rows, GLOBALS), np.float32)
        window[: len(states)], features[: len(states)] = e.window, e.features
        return np.asarray(guide_values(self.params, window, features, config=self.config))[: len(states)]


def untrained_like(guide: Guide, seed: int = 0) -> Guide:
    """`guide`'s network at initial weights drawn with `seed`, with its horizon: the arm that shows what
    learning changed (for one seed, the same network for every guide of one config; other seeds show
    how far untrained networks differ among themselves)."""
    params = init_guide(guide.config, jax.random.PRNGKey(seed))
    return Guide(guide.config, params, f"untrained (seed {seed})", guide.horizon)
