"""Thin parts: found as a brute force finds them, grown by --thicken (the shape kept), and named when a
search on a figure with thin limbs ends short."""

from __future__ import annotations

import itertools
import json

import numpy as np
from helpers import run_cli

from rllock.core.thickness import thicken, thin_voxels


def _thin_reference(grid: np.ndarray, width: int) -> np.ndarray:
    """Each voxel tried against every width^3 block that holds it."""
    thin = np.zeros_like(grid)
    for v in map(tuple, np.argwhere(grid)):
        covered = False
        for offset in itertools.product(range(width), repeat=3):
            lo = [c - o for c, o in zip(v, offset)]
            if min(lo) < 0 or any(lo[i] + width > grid.shape[i] for i in range(3)):
                continue
            if grid[lo[0] : lo[0] + width, lo[1] : lo[1] + width, lo[2] : lo[2] + width].all():
                covered = True
                break
        thin[v] = not covered
    return thin


def figure(limb: int = 4) -> np.ndarray:
    """A body with a head, two legs and two arms, each limb a rod one voxel thick."""
    g = np.zeros((4 + 2 * limb, 4, 9 + limb), dtype=bool)
    g[limb : limb + 4, :, limb : limb + 6] = True  # the body, on its legs
    g[limb + 0 : limb + 3, 0:3, limb + 6 : limb + 9] = True  # the head
    g[limb, 0, :limb] = g[limb + 3, 0, :limb] = True  # the legs
    g[:limb, 0, limb + 5] = g[limb + 4 :, 0, limb + 5] = True  # the arms
    return g


def _holds(big: np.ndarray, small: np.ndarray) -> bool:
    """Whether `small` lies inside `big` at some offset."""
    for offset in itertools.product(*(range(b - s + 1) for b, s in zip(big.shape, small.shape))):
        window = big[tuple(slice(o, o + s) for o, s in zip(offset, small.shape))]
        if window[small].all():
            return True
    return False


def test_thin_voxels_are_those_no_block_inside_the_shape_covers():
    rng = np.random.default_rng(0)
    for trial in range(20):
        grid = rng.random((6, 5, 7)) < 0.7
        for width in (2, 3):
            np.testing.assert_array_equal(thin_voxels(grid, width), _thin_reference(grid, width), str(trial))
    body = figure()
    thin = thin_voxels(body)
    assert thin.sum() == 4 * 4 and not thin[4:8, :, 4:10].any()  # the limbs, not the body or the head


def test_thicken_grows_the_thin_parts_until_none_is_left_and_keeps_the_shape():
    body = figure()
    grown = thicken(body, 3)
    assert not thin_voxels(grown).any() and _holds(grown, body)
    assert grown.sum() < 3 * body.sum()  # the limbs grew, not the whole shape
    solid = np.ones((4, 4, 4), dtype=bool)
    np.testing.assert_array_equal(thicken(solid, 3), solid)  # nothing thin: nothing changes


def test_a_figure_whose_limbs_stop_the_search_says_so_and_solves_thickened(tmp_path):
    np.save(tmp_path / "figure.npy", figure())
    shape = str(tmp_path / "figure.npy")
    code, out, err = run_cli(
        "solve", "--shape", shape, "--pieces", "16", "--time-limit", "3", "--probe", "0",
        "--out", str(tmp_path / "a"),
    )  # fmt: skip
    assert code == 1 and "thin parts: 16 of the 139 voxels" in out and "--thicken 3" in out, out + err
    code, out, err = run_cli(
        "solve", "--shape", shape, "--pieces", "16", "--thicken", "3", "--time-limit", "30",
        "--out", str(tmp_path / "b"),
    )  # fmt: skip
    assert code == 0 and "--thicken 3" in err, out + err
    doc = json.loads((tmp_path / "b" / "assembly_001" / "assembly.json").read_text())
    assert doc["shape"] == f"{shape} (--thicken 3)" and doc["verification"]["valid"] and doc["N"] > 139
    code, out, err = run_cli(
        "solve", "--shape", shape, "--pieces", "4", "--thicken", "1", "--out", str(tmp_path / "c")
    )
    assert code == 2 and "at least 2" in err and len(err.strip().splitlines()) == 1
