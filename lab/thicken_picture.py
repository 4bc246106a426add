"""Lab study, outside the installed package.
Question: What does `--thicken` do to a figure?
Answer: docs/thicken.png (docs/results.md, "Figures with thin limbs").

A mesh voxelized as `solve` does it, beside the same voxels with their thin parts grown
(`rllock.core.thickness.thicken`), the voxels it added in another colour.

    .venv/bin/python lab/thicken_picture.py MESH RESOLUTION WIDTH OUT.png   (homer.obj 24 3 docs/thicken.png)
"""

from __future__ import annotations

import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from rllock.core.shapes import load_shape  # noqa: E402
from rllock.core.thickness import thicken, thin_voxels  # noqa: E402


def shift_into(grid: np.ndarray, grown: np.ndarray) -> tuple[int, ...]:
    """Where `thicken`'s result (cropped to its own bounding box) holds `grid`: the shift at which every
    voxel of the figure is in the grown one."""
    room = [b - a for a, b in zip(grid.shape, grown.shape)]
    for shift in np.ndindex(*(r + 1 for r in room)):
        window = grown[tuple(slice(o, o + n) for o, n in zip(shift, grid.shape))]
        if (window | ~grid).all():
            return shift
    raise ValueError("the grown shape does not hold the figure")


def placed(mask: np.ndarray, shift: tuple[int, ...], shape: tuple[int, ...]) -> np.ndarray:
    out = np.zeros(shape, dtype=bool)
    out[tuple(slice(o, o + n) for o, n in zip(shift, mask.shape))] = mask
    return out


def main(mesh: str, resolution: int, width: int, out: str) -> None:
    grid = load_shape(mesh, resolution)
    grown = thicken(grid, width)  # cropped to its own bounding box, which can be larger than the grid's
    shift = shift_into(grid, grown)
    grid, thin = (placed(a, shift, grown.shape) for a in (grid, thin_voxels(grid, width)))
    fig = plt.figure(figsize=(10, 5.2), dpi=110)
    panels = (
        (
            grid,
            {"thin": thin, "rest": grid & ~thin},
            f"as voxelized: {int(grid.sum()):,} voxels, {int(thin.sum()):,} thin",
        ),
        (grown, {"rest": grid, "added": grown & ~grid}, f"--thicken {width}: {int(grown.sum()):,} voxels"),
    )
    colours = {"rest": "#b8bec6", "thin": "#d9534f", "added": "#5b9bd5"}
    for i, (shape, parts, title) in enumerate(panels):
        ax = fig.add_subplot(1, 2, i + 1, projection="3d")
        # Meshes stand along y (their up axis in most files): y drawn upwards.
        upright = (0, 2, 1)
        shape = np.transpose(shape, upright)
        filled = np.zeros(shape.shape, dtype=object)
        for name, mask in parts.items():
            filled[np.transpose(mask, upright)] = colours[name]
        ax.voxels(shape, facecolors=filled, edgecolor="#00000022", linewidth=0.2)
        ax.set_box_aspect(shape.shape, zoom=1.1)
        ax.view_init(elev=15, azim=-60)
        ax.set_axis_off()
        ax.set_title(title, fontsize=10)
    fig.suptitle(
        f"{mesh.rsplit('/', 1)[-1]} at resolution {resolution}: "
        "thin parts (red) and what --thicken adds (blue)",
        fontsize=11,
    )
    fig.savefig(out, bbox_inches="tight")


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4])
