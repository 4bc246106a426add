from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rllock.core.env import make_task
from rllock.errors import RLLockError
from rllock.search.network import (
    MASKED_LOGIT,
    Conv3,
    NetConfig,
    PolicyValueNet,
    Upsample2,
    chunk_logits,
    encode_batch,
    fit_canvas,
    init_params,
)


def test_shifted_convolution_equals_lax_conv():
    key_x, key_p = jax.random.split(jax.random.PRNGKey(0))
    x = jax.random.normal(key_x, (2, 4, 4, 4, 3))
    conv = Conv3(5)
    params = conv.init(key_p, x)
    kernel = params["params"]["kernel"].reshape(3, 3, 3, 3, 5)
    expected = jax.lax.conv_general_dilated(
        x, kernel, (1, 1, 1), "SAME", dimension_numbers=("NDHWC", "DHWIO", "NDHWC")
    )
    np.testing.assert_allclose(conv.apply(params, x), expected + params["params"]["bias"], atol=1e-5)


def test_encoding_planes():
    task = make_task("box:3x2x2", 4)  # N = 12, n = 3
    labels = np.zeros(12, np.int16)
    labels[[0, 1, 2]] = 1
    labels[[3, 4, 5]] = 2
    planes = encode_batch(task, labels[None], np.array([2]), 4)[0]
    assert planes.shape == (4, 4, 4, 7)
    assert planes[..., 0].sum() == 12 and planes[3:, :, :, 0].sum() == 0  # padding stays empty
    assert planes[..., 1].sum() == 6 and planes[..., 2].sum() == 6
    assert planes[..., 4].sum() == 3 and planes[..., 5].sum() == 3
    np.testing.assert_allclose(planes[..., 6].max(), 2 / 4)
    np.testing.assert_allclose(np.unique(planes[..., 3]), [0, 1 / 4, 2 / 4])
    first = encode_batch(task, np.zeros((1, 12), np.int16), np.array([0]), 4)[0]
    assert first[..., 5].sum() == 0  # no previous piece at the start


def test_chunk_logits_pool_their_voxels_and_mask_padding():
    voxel_logits = jnp.arange(8.0)[None]
    chunks = jnp.array([[[0, 1], [6, 7], [0, 0]]])
    valid = jnp.array([[True, True, False]])
    np.testing.assert_allclose(chunk_logits(voxel_logits, chunks, valid), [[0.5, 6.5, MASKED_LOGIT]])


def test_network_shapes_and_value_range():
    config = NetConfig(canvas=4, features=(4, 8))
    params = init_params(config, jax.random.PRNGKey(1))
    logits, value = PolicyValueNet(config).apply({"params": params}, jnp.ones((3, 4, 4, 4, 7)))
    assert logits.shape == (3, 64) and value.shape == (3,)
    assert bool(((value > 0) & (value < 1)).all())


def test_shapes_that_do_not_fit_the_canvas_are_errors():
    with pytest.raises(RLLockError, match="does not fit"):
        fit_canvas(make_task("cube6", 4), NetConfig(canvas=4))
    with pytest.raises(RLLockError, match="multiple of 4"):
        fit_canvas(make_task("cube3", 4), NetConfig(canvas=6))
    assert fit_canvas(make_task("cube4", 4), NetConfig(canvas=8)).canvas == 8


@pytest.mark.parametrize(
    "shape,features,canvas",
    [
        ("cube4", (16, 32, 64), 4),
        ("cube5", (16, 32, 64), 8),
        ("cube6", (16, 32, 64), 8),
        ("cube6", (8, 16), 6),
        ("box:7x3x2", (8,), 7),
    ],
)
def test_the_default_canvas_is_the_smallest_that_fits(shape, features, canvas):
    assert fit_canvas(make_task(shape, 2), NetConfig(features=features)).canvas == canvas


def test_upsampling_equals_flax_conv_transpose_with_the_same_parameters():
    """Upsample2 replaces nn.ConvTranspose (2x2x2, stride 2) and must read its parameters unchanged,
    so that checkpoints written with the old layer load and give the same outputs."""
    x = jax.random.normal(jax.random.PRNGKey(0), (2, 2, 3, 4, 5))
    reference = nn.ConvTranspose(6, (2, 2, 2), strides=(2, 2, 2))
    shapes = reference.init(jax.random.PRNGKey(1), x)["params"]
    keys = jax.random.split(jax.random.PRNGKey(2), 2)
    params = {
        "params": {
            "kernel": jax.random.normal(keys[0], shapes["kernel"].shape),
            "bias": jax.random.normal(keys[1], shapes["bias"].shape),
        }
    }
    np.testing.assert_allclose(Upsample2(6).apply(params, x), reference.apply(params, x), atol=1e-5)
