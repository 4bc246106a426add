"""Symmetry augmentation and self-imitation replay: the checkers must not tell a state from its symmetric
image, the augmented batch must be the mapped transitions, and the replay mix must hold its share."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from helpers import random_valid_states, raw_chunks

from rllock.core import compiled_checkers as checkers
from rllock.core.env import State, make_task
from rllock.core.topology import build_topology, symmetries
from rllock.learner.replay import ReplayBuffer
from rllock.search.base import Episode
from rllock.search.workload import augment


def _brute_force_count(grid: np.ndarray) -> int:
    """Symmetries by comparing whole grids: every axis permutation and reflection that maps the grid
    onto itself."""
    count = 0
    for axes in itertools.permutations(range(3)):
        moved = np.transpose(grid, axes)
        for flips in itertools.product((False, True), repeat=3):
            image = np.flip(moved, [a for a in range(3) if flips[a]]) if any(flips) else moved
            count += image.shape == grid.shape and np.array_equal(image, grid)
    return count


@pytest.mark.parametrize("shape", ["cube4", "box:2x3x4", "box:3x3x2", "ring"])
def test_symmetry_count_and_permutations(shape):
    topo = make_task(shape, 2).topology
    perms = symmetries(topo)
    assert len(perms) == _brute_force_count(topo.grid)
    np.testing.assert_array_equal(perms[0], np.arange(topo.size))  # identity first
    for p in perms:
        assert sorted(p.tolist()) == list(range(topo.size))
        # Face neighbours stay face neighbours: the map is a rigid motion of the voxels.
        for v in range(topo.size):
            assert {p[u] for u in topo.nbr[v] if u >= 0} == {u for u in topo.nbr[p[v]] if u >= 0}


def test_an_l_shape_has_only_its_mirror():
    grid = np.zeros((3, 3, 1), bool)
    grid[:, 0, 0] = grid[0, :, 0] = True
    perms = symmetries(build_topology(grid))
    assert len(perms) == 4 == _brute_force_count(grid)  # identity, swap x/y, and both with z mirrored


@pytest.mark.parametrize("removal", ["straight", "path"])
def test_checkers_agree_on_symmetric_images(removal):
    task = make_task("cube4", 7, removal)
    topo = task.topology
    perms = symmetries(topo)
    rng = np.random.default_rng(3)
    compared = accepted = 0
    for state in random_valid_states(task, rng, episodes=6):
        chunks = raw_chunks(task, state, rng, 40)
        if len(chunks) == 0:
            continue
        want = checkers.check_chunks(topo.arrays, state.labels, state.placed + 1, chunks, removal == "path")
        for p in perms[rng.choice(len(perms), 6, replace=False)]:
            labels = np.empty_like(state.labels)
            labels[p] = state.labels
            got = checkers.check_chunks(
                topo.arrays, labels, state.placed + 1, p[chunks].astype(np.int32), removal == "path"
            )
            np.testing.assert_array_equal(got, want)
            compared += len(chunks)
        accepted += int((want == checkers.ALL_CHECKS).sum())
    assert compared > 1000 and accepted > 10  # both outcomes were exercised


def test_augment_maps_labels_and_chunks_by_one_permutation_per_row():
    rng = np.random.default_rng(0)
    n_vox, m, n, batch = 12, 3, 2, 16
    perms = np.stack([rng.permutation(n_vox) for _ in range(5)])
    sample = {
        "labels": rng.integers(0, 4, (batch, n_vox)).astype(np.int8),
        "chunks": rng.integers(0, n_vox, (batch, m, n)).astype(np.int16),
        "pi": rng.random((batch, m)).astype(np.float32),
        "z": rng.random(batch).astype(np.float32),
    }
    out = augment(sample, perms, seed=1)
    assert out["chunks"].dtype == np.int16 and out["labels"].dtype == np.int8
    np.testing.assert_array_equal(out["pi"], sample["pi"])
    used = set()
    for b in range(batch):
        # Exactly one of the permutations explains the row: labels'[p] = labels and chunks' = p[chunks].
        fits = [
            i
            for i, p in enumerate(perms)
            if np.array_equal(out["labels"][b][p], sample["labels"][b])
            and np.array_equal(out["chunks"][b], p[sample["chunks"][b]])
        ]
        assert len(fits) >= 1
        used.update(fits)
    assert len(used) > 1  # rows draw different symmetries


def _episode(success: bool, length: int, n_vox: int = 8, m: int = 2, n: int = 2) -> Episode:
    return Episode(
        labels=np.full((length, n_vox), int(success), np.int8),
        placed=np.arange(length, dtype=np.int16),
        chunks=np.zeros((length, m, n), np.int16),
        num_valid=np.ones(length, np.int16),
        pi=np.full((length, m), 0.5, np.float32),
        z=np.zeros(length, np.float32),
        success=success,
        final=State(np.zeros(n_vox, np.int16), length),
        actions=np.zeros(length, np.int16),
    )


def test_success_fraction_mixes_successful_transitions(tmp_path):
    buf = ReplayBuffer(100, 8, 2, 2)
    buf.add_many([_episode(False, 5) for _ in range(10)])
    uniform = buf.sample(64, seed=0, success_fraction=0.5)  # no success yet: plain uniform replay
    assert uniform["labels"].shape == (64, 8) and not uniform["labels"].any()
    buf.add(_episode(True, 3))
    assert buf.counts().successes == 3
    mixed = buf.sample(64, seed=0, success_fraction=0.5)
    wins = mixed["labels"][:, 0] == 1
    assert wins[:32].all() and wins.sum() < 40  # the 32 drawn from wins, the rest mostly from the 50 others
    plain = buf.sample(64, seed=0)
    assert plain["labels"][:, 0].sum() < 16  # 3 of 53 transitions
    buf.snapshot(str(tmp_path / "replay.npz"))
    again = ReplayBuffer(100, 8, 2, 2)
    again.restore(str(tmp_path / "replay.npz"))
    assert again.counts().successes == 3
    np.testing.assert_array_equal(again.sample(64, seed=0, success_fraction=0.5)["labels"], mixed["labels"])
