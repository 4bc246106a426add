"""Transitions on the canvas: how a multi-task replay buffer stores states of different shapes side by side.

A single-task run stores a state as labels per voxel of its one shape. Shapes differ across a multi-task
run, so there a state is stored as canvas labels (int8[C^3], -1 off the shape; `network.to_canvas`) and
its candidates as canvas indices, padded with -1 to the run's largest piece size. The learner encodes
these directly (`network.encode_canvas`) and needs no task.

Augmentation: each transition is mapped through one of the 48 rotations and reflections of its shape's
bounding box (axis permutations, then mirror images within the box), which keeps the shape at the
canvas origin. The image is a state of the rotated or mirrored shape, with the same candidates (mapped),
search policy and value: slides, contacts and connectivity are all preserved by these maps.

Several canvases in one run (`rllock.core.tasks`): states are stored on the run's largest canvas, and a
batch is learned from on the canvas its states were played on (`crop_canvas`): since shapes sit at the
origin, a smaller canvas is the store's corner, and its cells keep their (x, y, z).
"""

from __future__ import annotations

import functools
import itertools

import numpy as np

from rllock.core.env import Task
from rllock.search.base import Episode
from rllock.search.network import canvas_index, to_canvas

PERMUTATIONS = tuple(itertools.permutations(range(3)))
FLIPS = tuple(itertools.product((False, True), repeat=3))


def canvas_episode(task: Task, episode: Episode, canvas: int, piece_size: int) -> Episode:
    """`episode` with canvas labels [T, C^3] and candidates as canvas indices [T, M, piece_size] (-1 pads
    each chunk beyond the task's n)."""
    t, m, n = episode.chunks.shape
    chunks = np.full((t, m, piece_size), -1, np.int16)
    chunks[:, :, :n] = canvas_index(task, canvas)[episode.chunks.astype(np.int64)]
    chunks[np.arange(m)[None, :] >= episode.num_valid[:, None]] = -1
    return Episode(
        to_canvas(task, episode.labels, canvas),
        episode.placed,
        chunks,
        episode.num_valid,
        episode.pi,
        episode.z,
        episode.success,
        episode.final,
        episode.actions,
    )


def crop_canvas(sample: dict[str, np.ndarray], store: int, canvas: int) -> dict[str, np.ndarray]:
    """Transitions stored on a `store`^3 canvas as the same transitions on the `canvas`^3 corner, which
    must hold their shapes: labels [B, store^3] -> [B, canvas^3], candidate indices remapped (-1 stays)."""
    if canvas == store:
        return sample
    labels = sample["labels"].reshape(-1, store, store, store)
    if (
        (labels[:, canvas:] >= 0).any()
        or (labels[:, :, canvas:] >= 0).any()
        or (labels[..., canvas:] >= 0).any()
    ):
        raise ValueError(f"a stored shape does not fit the {canvas}^3 canvas")
    chunks = sample["chunks"]
    x, rest = np.divmod(chunks.astype(np.int64), store * store)
    y, z = np.divmod(rest, store)
    cropped = np.where(chunks >= 0, (x * canvas + y) * canvas + z, -1).astype(chunks.dtype)
    return {
        **sample,
        "labels": np.ascontiguousarray(labels[:, :canvas, :canvas, :canvas]).reshape(len(labels), -1),
        "chunks": cropped,
    }


@functools.cache
def box_maps(dims: tuple[int, int, int], canvas: int) -> np.ndarray:
    """int32[48, C^3]: for each rotation or reflection of a box of `dims` at the canvas origin, where
    each canvas cell inside the box goes (-1 for cells outside it)."""
    coords = np.argwhere(np.ones(dims, bool))
    src = (coords[:, 0] * canvas + coords[:, 1]) * canvas + coords[:, 2]
    maps = np.full((len(PERMUTATIONS) * len(FLIPS), canvas**3), -1, np.int32)
    for i, (perm, flip) in enumerate(itertools.product(PERMUTATIONS, FLIPS)):
        moved = coords[:, perm]
        size = np.array(dims)[list(perm)]
        moved = np.where(flip, size - 1 - moved, moved)
        maps[i, src] = (moved[:, 0] * canvas + moved[:, 1]) * canvas + moved[:, 2]
    return maps


def shape_dims(labels: np.ndarray, canvas: int) -> np.ndarray:
    """int[B, 3]: the bounding box of each canvas state's shape (which sits at the origin)."""
    on = labels.reshape(-1, canvas, canvas, canvas) >= 0
    axes = [on.any(axis=(2, 3)), on.any(axis=(1, 3)), on.any(axis=(1, 2))]
    # numpy's stub types any() over some axes as maybe a scalar; over two of four axes it is a [B, C] array.
    return np.stack([canvas - np.argmax(a[:, ::-1], axis=1) for a in axes], axis=1)  # type: ignore[index]


def augment_canvas(sample: dict[str, np.ndarray], canvas: int, seed: int) -> dict[str, np.ndarray]:
    """Each canvas transition mapped through one of its box's 48 maps, drawn uniformly (module
    docstring)."""
    labels, chunks = sample["labels"], sample["chunks"]
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, len(PERMUTATIONS) * len(FLIPS), size=len(labels))
    out_labels = np.full_like(labels, -1)
    out_chunks = chunks.copy()
    for row, (dims, pick) in enumerate(zip(shape_dims(labels, canvas), picks)):
        where = box_maps(tuple(int(d) for d in dims), canvas)[pick]
        inside = where >= 0
        out_labels[row, where[inside]] = labels[row, inside]
        real = chunks[row] >= 0
        out_chunks[row][real] = where[chunks[row][real]]
    return {**sample, "labels": out_labels, "chunks": out_chunks}
