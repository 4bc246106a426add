"""Thin parts of a shape, and growing them: a figure's arms, legs, ears and tails voxelize one or two voxels
thick, and there a piece has little room to hold or be held, so a search that places most pieces ends short
on them. `thin_voxels` finds them (no block of width^3 voxels inside the shape covers them); `thicken` grows
them until one does, leaving the rest of the shape as it is."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

THIN_WIDTH = 3
"""The width a part needs not to count as thin: a 3^3 block fits in it."""


def thin_voxels(grid: np.ndarray, width: int = THIN_WIDTH) -> np.ndarray:
    """The voxels of the boolean `grid` that no block of width^3 voxels lying inside the shape covers
    (the shape less its morphological opening by that block)."""
    grid = np.asarray(grid, dtype=bool)
    if width <= 1:
        return np.zeros_like(grid)
    opened = ndimage.binary_opening(grid, structure=np.ones((width,) * 3, dtype=bool))
    return grid & ~opened


def thicken(grid: np.ndarray, width: int = THIN_WIDTH) -> np.ndarray:
    """`grid` with its thin parts (`thin_voxels`) grown by a voxel all round, again while some are left,
    at most `width` times; every voxel of the shape is kept. The result may be larger than `grid`: a
    limb at the edge of the bounding box grows past it."""
    if width < 1:
        raise ValueError(f"a width is at least 1 voxel, got {width}")
    out = np.pad(np.asarray(grid, dtype=bool), width)
    grow = np.ones((3, 3, 3), dtype=bool)
    for _ in range(width):
        thin = thin_voxels(out, width)
        if not thin.any():
            break
        out |= ndimage.binary_dilation(thin, structure=grow)
    found = np.argwhere(out)
    lo, hi = found.min(axis=0), found.max(axis=0) + 1
    return out[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]


THIN_SHARE = 0.05
"""Thin parts are worth a word (and a try with them grown) when they hold at least this share of a shape's
voxels, or a piece's worth."""


def thin_matters(thin: int, size: int, piece_size: int) -> bool:
    """Whether `thin` thin voxels of a shape of `size` are worth a word, with pieces of `piece_size`."""
    return thin >= max(piece_size, THIN_SHARE * size)


def thin_enough_to_matter(grid: np.ndarray, piece_size: int) -> int | None:
    """How many of `grid`'s voxels are thin (`thin_voxels`), when that is worth saying; else None."""
    thin = int(thin_voxels(grid).sum())
    return thin if thin_matters(thin, int(grid.sum()), piece_size) else None
