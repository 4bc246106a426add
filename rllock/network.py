"""The policy-value network: a 3D U-Net over a fixed cubic canvas, and the state encoding it reads.

Encoding (`encode_state`), channels-last float planes on a C x C x C canvas; the shape sits at the
canvas origin and the rest is padding (all planes 0 there):
  0  shape      1 on every voxel of the input shape
  1  remaining  1 on the remaining volume R_i
  2  placed     1 on every placed piece P1..Pi
  3  order      j / K on the voxels of piece Pj (0 elsewhere): which piece came when
  4  key        1 on the key P1
  5  previous   1 on the last placed piece Pi (the next piece starts next to it)
  6  progress   i / K on every voxel of the shape
Policy: the U-Net gives one logit per canvas voxel; a candidate chunk's logit is the mean of its voxels'
logits (so the policy generalises across the chunks sampled at a node, whatever their number), and
padding candidates (fewer than M_c accepted) are masked. Value: global average of the bottleneck
features through a small MLP and a sigmoid, since the target (the cumulative reward, at most
(K-1)/K) lies in [0, 1].
"""

from __future__ import annotations


import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from rllock.env import Task
from rllock.config import NetConfig
from rllock.errors import RLLockError

PLANES = 7
MASKED_LOGIT = -1e9


def check_fits(task: Task, config: NetConfig) -> None:
    canvas = config.canvas
    if max(task.topology.dims) > canvas:
        raise RLLockError(f"shape {task.shape_name} {task.topology.dims} does not fit the {canvas}^3 canvas; "
                          f"use a larger --canvas")
    step = 1 << (len(config.features) - 1)
    if canvas % step != 0:
        raise RLLockError(f"the canvas side must be a multiple of {step}, got {canvas}")


def canvas_index(task: Task, canvas: int) -> np.ndarray:
    """int32[N]: the flat canvas index of each shape voxel."""
    x, y, z = task.topology.coords.T
    return ((x * canvas + y) * canvas + z).astype(np.int32)


def encode_batch(task: Task, labels: np.ndarray, placed: np.ndarray, canvas: int) -> np.ndarray:
    """labels int[B, N], placed int[B] -> float32 planes [B, C, C, C, PLANES] (module docstring)."""
    k = task.pieces
    batch = labels.shape[0]
    flat = np.zeros((batch, canvas**3, PLANES), dtype=np.float32)
    idx = canvas_index(task, canvas)
    placed = np.asarray(placed).reshape(-1, 1)
    flat[:, idx, 0] = 1.0
    flat[:, idx, 1] = labels == 0
    flat[:, idx, 2] = labels > 0
    flat[:, idx, 3] = labels / k
    flat[:, idx, 4] = labels == 1
    flat[:, idx, 5] = (labels == placed) & (placed > 0)
    flat[:, idx, 6] = placed / k
    return flat.reshape(batch, canvas, canvas, canvas, PLANES)


class Conv3(nn.Module):
    """A 3x3x3 'SAME' convolution as 27 shifted copies and one matmul: on the CPU this is about twice
    as fast as XLA's convolution for these small volumes (tests check it equals lax.conv)."""

    features: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        c_in = x.shape[-1]
        kernel = self.param("kernel", nn.initializers.lecun_normal(), (27 * c_in, self.features))
        bias = self.param("bias", nn.initializers.zeros, (self.features,))
        return shifted_columns(x) @ kernel + bias


def shifted_columns(x: jax.Array) -> jax.Array:
    """[B, D, H, W, C] -> [B, D, H, W, 27 C]: each voxel's 3x3x3 neighbourhood (zero padded), offsets
    in (dx, dy, dz) row-major order, matching a DHWIO kernel reshaped to (27 C, out)."""
    d, h, w = x.shape[1:4]
    xp = jnp.pad(x, ((0, 0), (1, 1), (1, 1), (1, 1), (0, 0)))
    return jnp.concatenate(
        [xp[:, i : i + d, j : j + h, k : k + w, :] for i in range(3) for j in range(3) for k in range(3)], axis=-1
    )


class _Block(nn.Module):
    features: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for _ in range(2):
            x = Conv3(self.features)(x)
            x = nn.LayerNorm()(x)
            x = nn.relu(x)
        return x


class PolicyValueNet(nn.Module):
    """planes [B, C, C, C, P] -> (voxel logits [B, C^3], value [B])."""

    config: NetConfig

    @nn.compact
    def __call__(self, planes: jax.Array) -> tuple[jax.Array, jax.Array]:
        skips = []
        x = planes
        for f in self.config.features[:-1]:
            x = _Block(f)(x)
            skips.append(x)
            x = nn.max_pool(x, (2, 2, 2), strides=(2, 2, 2))
        x = _Block(self.config.features[-1])(x)
        pooled = x.mean(axis=(1, 2, 3))
        for f, skip in zip(reversed(self.config.features[:-1]), reversed(skips)):
            x = nn.ConvTranspose(f, (2, 2, 2), strides=(2, 2, 2))(x)
            x = _Block(f)(jnp.concatenate([x, skip], axis=-1))
        voxel_logits = nn.Conv(1, (1, 1, 1))(x)[..., 0]
        h = nn.relu(nn.Dense(self.config.value_hidden)(pooled))
        value = nn.sigmoid(nn.Dense(1)(h))[:, 0]
        return voxel_logits.reshape(planes.shape[0], -1), value


def chunk_logits(voxel_logits: jax.Array, chunks: jax.Array, valid: jax.Array) -> jax.Array:
    """voxel_logits [B, C^3], chunks [B, M, n] canvas indices, valid [B, M] -> logits [B, M]."""
    gathered = jnp.take_along_axis(voxel_logits[:, None, :], chunks, axis=2)
    return jnp.where(valid, gathered.mean(axis=-1), MASKED_LOGIT)


def init_params(config: NetConfig, key: jax.Array) -> dict:
    dummy = jnp.zeros((1, config.canvas, config.canvas, config.canvas, PLANES), jnp.float32)
    return PolicyValueNet(config).init(key, dummy)["params"]
