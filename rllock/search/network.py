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
and, for networks that serve many tasks (`NetConfig.task_planes`, `rllock train --tasks`), what a single
task's network never needs to be told:
  7  piece size n / 32 on every voxel of the shape (n = floor(N / K); the shape's size N is plane 0's sum)
  8  pieces     K / 32 on every voxel of the shape
`encode_batch` writes them for one task's states (the search); `encode_canvas` computes the same planes
from canvas labels (`to_canvas`: -1 off the shape), the form in which a multi-task replay buffer stores
states of different shapes side by side.
Policy: the U-Net gives one logit per canvas voxel; a candidate chunk's logit is the mean of its voxels'
logits (so the policy generalises across the chunks sampled at a node, whatever their number), and
padding candidates (fewer than M_c accepted) are masked. Value: global average of the bottleneck
features through a small MLP and a sigmoid, since the target (the cumulative reward, at most
(K-1)/K) lies in [0, 1].
"""

from __future__ import annotations

from functools import partial

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from rllock.config import NetConfig
from rllock.core.env import Task
from rllock.errors import RLLockError

PLANES = 7
TASK_PLANES = 2
TASK_SCALE = 32.0  # n and K are divided by this in planes 7 and 8: values near [0, 1] for these tasks
MASKED_LOGIT = -1e9


def planes_of(config: NetConfig) -> int:
    """How many input planes a network of `config` reads."""
    return PLANES + (TASK_PLANES if config.task_planes else 0)


def fit_canvas(task: Task, config: NetConfig, canvas_of: str | None = None) -> NetConfig:
    """`config` with a concrete canvas for `task` (the smallest that fits, unless one is set); a shape
    that does not fit the canvas is an error. `canvas_of`: where a fixed canvas came from (a
    checkpoint), for that error."""
    fitted = config.fitted(task.topology.dims)
    canvas = fitted.canvas
    assert canvas is not None
    if max(task.topology.dims) > canvas:
        where = f" of {canvas_of}" if canvas_of else "; use a larger --canvas"
        raise RLLockError(
            f"shape {task.shape_name} {task.topology.dims} does not fit the {canvas}^3 canvas{where}"
        )
    if canvas % config.levels_step() != 0:
        raise RLLockError(f"the canvas side must be a multiple of {config.levels_step()}, got {canvas}")
    return fitted


def canvas_index(task: Task, canvas: int) -> np.ndarray:
    """int32[N]: the flat canvas index of each shape voxel."""
    x, y, z = task.topology.coords.T
    return ((x * canvas + y) * canvas + z).astype(np.int32)


def to_canvas(task: Task, labels: np.ndarray, canvas: int) -> np.ndarray:
    """labels int[B, N] -> int8 canvas labels [B, C^3]: -1 off the shape, else the voxel's label."""
    out = np.full((labels.shape[0], canvas**3), -1, np.int8)
    out[:, canvas_index(task, canvas)] = labels
    return out


def encode_canvas(
    labels: np.ndarray, placed: np.ndarray, pieces: np.ndarray, canvas: int, task_planes: bool = False
) -> np.ndarray:
    """Canvas labels int[B, C^3] (-1 off the shape), placed int[B], K int[B] -> float32 planes
    [B, C, C, C, P] (module docstring); P = PLANES, plus TASK_PLANES with `task_planes`."""
    batch = labels.shape[0]
    on = labels >= 0
    placed = np.asarray(placed).reshape(-1, 1).astype(np.float32)
    k = np.asarray(pieces).reshape(-1, 1).astype(np.float32)
    planes = [
        on,
        labels == 0,
        labels > 0,
        np.where(on, labels, 0) / k,
        labels == 1,
        (labels == placed) & (placed > 0),
        on * (placed / k),
    ]
    if task_planes:
        size = on.sum(axis=1, keepdims=True)
        planes += [on * (size // k / TASK_SCALE), on * (k / TASK_SCALE)]
    flat = np.stack(planes, axis=-1).astype(np.float32)
    return flat.reshape(batch, canvas, canvas, canvas, len(planes))


def encode_batch(
    task: Task, labels: np.ndarray, placed: np.ndarray, canvas: int, task_planes: bool = False
) -> np.ndarray:
    """labels int[B, N], placed int[B] -> float32 planes [B, C, C, C, P] (module docstring). The search's
    hot path: it writes the shape's voxels only; `encode_canvas` gives the same planes from canvas
    labels."""
    k = task.pieces
    batch = labels.shape[0]
    flat = np.zeros((batch, canvas**3, PLANES + (TASK_PLANES if task_planes else 0)), dtype=np.float32)
    idx = canvas_index(task, canvas)
    placed = np.asarray(placed).reshape(-1, 1)
    flat[:, idx, 0] = 1.0
    flat[:, idx, 1] = labels == 0
    flat[:, idx, 2] = labels > 0
    flat[:, idx, 3] = labels / k
    flat[:, idx, 4] = labels == 1
    flat[:, idx, 5] = (labels == placed) & (placed > 0)
    flat[:, idx, 6] = placed / k
    if task_planes:
        flat[:, idx, 7] = task.piece_size / TASK_SCALE
        flat[:, idx, 8] = k / TASK_SCALE
    return flat.reshape(batch, canvas, canvas, canvas, flat.shape[-1])


class Conv3(nn.Module):
    """A 3x3x3 'SAME' convolution as one matmul over the 9 (y, z) shifts, whose 3 outputs per voxel (one
    per x offset) are summed with x shifts. On the CPU this is several times faster than XLA's convolution and
    than a matmul over all 27 shifts for these small volumes (tests check it equals lax.conv). The
    kernel is stored as (27 C_in, out), offsets (dx, dy, dz) row-major: a DHWIO kernel reshaped."""

    features: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        c_in = x.shape[-1]
        kernel = self.param("kernel", nn.initializers.lecun_normal(), (27 * c_in, self.features))
        bias = self.param("bias", nn.initializers.zeros, (self.features,))
        return conv3(x, kernel.reshape(3, 3, 3, c_in, self.features)) + bias


def conv3(x: jax.Array, kernel: jax.Array) -> jax.Array:
    """x [B, D, H, W, C], kernel DHWIO [3, 3, 3, C, F] -> [B, D, H, W, F], zero 'SAME' padding."""
    d, h, w, c = x.shape[1:]
    f = kernel.shape[-1]
    yz = jnp.pad(x, ((0, 0), (0, 0), (1, 1), (1, 1), (0, 0)))
    columns = jnp.concatenate(
        [yz[:, :, j : j + h, k : k + w, :] for j in range(3) for k in range(3)], axis=-1
    )
    by_dx = (columns @ jnp.transpose(kernel, (1, 2, 3, 0, 4)).reshape(9 * c, 3 * f)).reshape(
        *x.shape[:4], 3, f
    )
    padded = jnp.pad(by_dx, ((0, 0), (1, 1), (0, 0), (0, 0), (0, 0), (0, 0)))
    return padded[:, :d, :, :, 0] + padded[:, 1 : 1 + d, :, :, 1] + padded[:, 2 : 2 + d, :, :, 2]


class Upsample2(nn.Module):
    """flax's `ConvTranspose(features, (2, 2, 2), strides=(2, 2, 2))`, with the same parameters, as one
    matmul and a depth-to-space reshape: the 2x2x2 windows do not overlap, so each input voxel alone
    makes its 8 output voxels. XLA's transposed convolution is much slower on the CPU here."""

    features: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        b, d, h, w, c = x.shape
        kernel = self.param("kernel", nn.initializers.lecun_normal(), (2, 2, 2, c, self.features))
        bias = self.param("bias", nn.initializers.zeros, (self.features,))
        # lax.conv_transpose (which flax uses) applies the kernel flipped along each spatial axis.
        flipped = kernel[::-1, ::-1, ::-1]
        y = x.reshape(-1, c) @ jnp.transpose(flipped, (3, 0, 1, 2, 4)).reshape(c, 8 * self.features)
        y = y.reshape(b, d, h, w, 2, 2, 2, self.features).transpose(0, 1, 4, 2, 5, 3, 6, 7)
        return y.reshape(b, 2 * d, 2 * h, 2 * w, self.features) + bias


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
        for i, (f, skip) in enumerate(zip(reversed(self.config.features[:-1]), reversed(skips))):
            x = Upsample2(f, name=f"ConvTranspose_{i}")(x)  # the name flax gave it: old checkpoints load
            x = _Block(f)(jnp.concatenate([x, skip], axis=-1))
        voxel_logits = nn.Conv(1, (1, 1, 1))(x)[..., 0]
        h = nn.relu(nn.Dense(self.config.value_hidden)(pooled))
        value = nn.sigmoid(nn.Dense(1)(h))[:, 0]
        return voxel_logits.reshape(planes.shape[0], -1), value


def chunk_logits(voxel_logits: jax.Array, chunks: jax.Array, valid: jax.Array) -> jax.Array:
    """voxel_logits [B, C^3], chunks [B, M, n] canvas indices, valid [B, M] -> logits [B, M]. Index -1
    pads a chunk shorter than n (a multi-task batch mixes piece sizes): the mean is over real voxels."""
    real = chunks >= 0
    gathered = jnp.take_along_axis(voxel_logits[:, None, :], jnp.where(real, chunks, 0), axis=2)
    mean = jnp.sum(jnp.where(real, gathered, 0.0), axis=-1) / jnp.maximum(real.sum(axis=-1), 1)
    return jnp.where(valid, mean, MASKED_LOGIT)


@partial(jax.jit, static_argnums=0)
def init_params(config: NetConfig, key: jax.Array) -> dict:
    """Fresh parameters for `config`, initialised as one compiled program: run op by op, the network's
    initialisation compiles each of its many small operations on its own, most of a fresh start."""
    dummy = jnp.zeros((1, config.canvas, config.canvas, config.canvas, planes_of(config)), jnp.float32)
    return PolicyValueNet(config).init(key, dummy)["params"]


def params_template(config: NetConfig) -> dict:
    """The parameters' structure, shapes and dtypes, without computing them: what a restore reads into."""
    return jax.eval_shape(lambda key: init_params(config, key), jax.random.PRNGKey(0))
