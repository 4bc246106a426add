"""The guide network's replay buffer and learner (`rllock train-guide`).

The buffer holds encoded search states (`rllock.search.guide.encode`: a window and features, both of a
fixed size whatever the shape) with their value targets, in a ring. The learner minimises the binary
cross-entropy between the network's value and the target (the share of the rollouts from the state that
reached an assembly, `actors.guide_actor`), with Adam; its step is a pure jitted function.
"""

from __future__ import annotations

import os
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

from learner.learner import AdamState
from rllock.config import GuideConfig
from rllock.errors import RLLockError
from rllock.process import peak_rss_mb
from rllock.search.base import BufferCounts
from rllock.search.guide import CHANNELS, GLOBALS, GuideNet, init_guide


class GuideBuffer:
    """Encoded states and targets; the oldest are overwritten once `capacity` is reached."""

    def __init__(self, capacity: int, window: int):
        self.capacity = capacity
        self.window = np.zeros((capacity, window, window, window, CHANNELS), np.int8)
        self.features = np.zeros((capacity, GLOBALS), np.float32)
        self.target = np.zeros(capacity, np.float32)
        self.size = self.cursor = self.added = self.received_bytes = 0

    def add(self, window: np.ndarray, features: np.ndarray, target: np.ndarray) -> BufferCounts:
        """Add a search's states; returns the counts after it."""
        for i in range(len(target)):
            at = self.cursor
            self.window[at], self.features[at], self.target[at] = window[i], features[i], target[i]
            self.cursor = (at + 1) % self.capacity
            self.size = min(self.size + 1, self.capacity)
            self.added += 1
        self.received_bytes += window.nbytes + features.nbytes + target.nbytes
        return self.counts()

    def sample(self, batch: int, seed: int) -> dict[str, np.ndarray]:
        idx = np.random.default_rng(seed).integers(0, self.size, size=batch)
        return {"window": self.window[idx], "features": self.features[idx], "target": self.target[idx]}

    def counts(self) -> BufferCounts:
        solved = int((self.target[: self.size] >= 1.0).sum())
        return BufferCounts(self.size, self.added, solved, self.received_bytes, peak_rss_mb())

    def snapshot(self, path: str) -> None:
        """Write the buffer to `path` atomically (a temporary file renamed over it)."""
        tmp = Path(path).with_suffix(".tmp.npz")
        arrays = {name: getattr(self, name)[: self.size] for name in ("window", "features", "target")}
        np.savez(tmp, size=self.size, cursor=self.cursor, added=self.added, **arrays)
        os.replace(tmp, path)

    def restore(self, path: str) -> int:
        with np.load(path) as data:
            size = int(data["size"])
            if size > self.capacity or data["window"].shape[1:] != self.window.shape[1:]:
                raise RLLockError(
                    f"replay snapshot {path} holds {size} states of window {data['window'].shape[1]}: "
                    f"resume with the --buffer-capacity and --window it was made with"
                )
            for name in ("window", "features", "target"):
                getattr(self, name)[:size] = data[name]
            self.size, self.added = size, int(data["added"])
            self.cursor = int(data["cursor"]) % self.capacity
        return size


def guide_loss(params, config: GuideConfig, window, features, target):
    logits = GuideNet(config).apply({"params": params}, window, features)
    return optax.sigmoid_binary_cross_entropy(logits, target).mean()


@partial(jax.jit, static_argnames=("config", "optimizer"))
def guide_step(params, opt_state, batch, *, config: GuideConfig, optimizer: optax.GradientTransformation):
    loss, grads = jax.value_and_grad(guide_loss)(params, config, *batch)
    updates, opt_state = optimizer.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state, loss


class GuideLearner(AdamState):
    """The guide network's learner: its parameters, optimizer state, step and PRNG key (`AdamState`)."""

    def __init__(self, config: GuideConfig, learning_rate: float, key: jax.Array):
        super().__init__(partial(init_guide, config), learning_rate, key)
        self.config = config

    def update(self, sample: dict[str, np.ndarray]) -> float:
        batch = (
            jnp.asarray(sample["window"], jnp.float32),
            jnp.asarray(sample["features"]),
            jnp.asarray(sample["target"]),
        )
        self.params, self.opt_state, loss = guide_step(
            self.params, self.opt_state, batch, config=self.config, optimizer=self.optimizer
        )
        self.step += 1
        return float(loss)
