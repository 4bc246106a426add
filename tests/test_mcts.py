from __future__ import annotations

import gc

import jax
import numpy as np
import pytest
from helpers import untrained_episodes

from rllock.core.env import final_labels, initial_state, make_task
from rllock.core.verifier import verify_labels
from rllock.search.base import derive_seed, group_sizes
from rllock.search.mcts import (
    ChunkStore,
    MCTSConfig,
    bounded_value,
    expand_rows,
    play_groups,
    searchers,
)
from rllock.search.network import NetConfig, init_params

SMALL = MCTSConfig(simulations=8, max_considered=4, raw_samples=256, candidates=8)


def test_expansion_rewards_terminals_and_memo():
    task = make_task("box:4x4x2", 4)  # n = 8
    store = ChunkStore(task, SMALL, 4, seed=0)
    root = store.add(initial_state(task))
    assert 0 < len(store.cands[root]) <= SMALL.candidates
    kids, reward, discount, floor, cap, planes, chunks, valid = expand_rows(
        store, np.array([root, root]), np.array([0, 0])
    )
    assert kids[0] == kids[1] and store.child(root, 0) == kids[0]  # the same (node, action) -> one node
    np.testing.assert_allclose(reward, 1 / 4)
    np.testing.assert_allclose(floor, 1 / 4)  # a live chunk node has an accepted candidate
    np.testing.assert_allclose(cap, 2 / 4)  # one piece placed, two still to place for K = 4
    assert planes.shape == (2, 4, 4, 4, 7) and valid[0].sum() == len(store.cands[kids[0]])
    # An action past the candidates, or any action below a terminal node, earns nothing and stays put.
    short = store.add(initial_state(task))
    store.cands[short] = store.cands[short][:3]  # a node with fewer candidates than M_c
    k, r, d, *_ = expand_rows(store, np.array([short]), np.array([5]))
    assert (k[0], r[0], d[0]) == (short, 0.0, 0.0)
    dead = store.add(initial_state(task))
    store.cands[dead] = store.cands[dead][:0]
    k, r, d, *_ = expand_rows(store, np.array([dead]), np.array([0]))
    assert (k[0], r[0], d[0]) == (dead, 0.0, 0.0)


def test_child_values_are_clipped_to_what_is_known():
    value = np.array([0.0, 0.9, 0.3, 0.9], np.float32)
    floor = np.array([0.25, 0.25, 0.25, 0.25], np.float32)
    discount = np.array([1.0, 1.0, 1.0, 0.0], np.float32)  # the last child is terminal
    cap = np.array([0.5, 0.5, 0.5, 0.0], np.float32)
    np.testing.assert_allclose(np.asarray(bounded_value(value, discount, floor, cap)), [0.25, 0.5, 0.3, 0.0])


@pytest.fixture(scope="module")
def episodes():
    return untrained_episodes(ChunkStore, SMALL, batch=6, seed=3)


def test_episode_records_are_consistent(episodes):
    task, eps = episodes
    assert len(eps) == 6 and any(e.success for e in eps)
    for e in eps:
        t = len(e.z)
        assert t >= 1 and list(e.placed) == list(range(t))
        np.testing.assert_allclose(e.z, (e.final.placed - e.placed) / task.pieces)
        for s in range(t):
            m = e.num_valid[s]
            assert m > 0 and np.isclose(e.pi[s, :m].sum(), 1, atol=1e-5) and np.allclose(e.pi[s, m:], 0)
        assert e.success == (e.final.placed == task.pieces - 1)


def test_successful_episodes_are_valid_assemblies(episodes):
    task, eps = episodes
    for e in eps:
        if e.success:
            assert verify_labels(task.topology.to_grid(final_labels(task, e.final))).valid


def test_groups_in_threads_share_one_compiled_search_and_play_as_each_would_alone():
    """play_groups runs lockstep groups concurrently (XLA and numba without the GIL) through one shared
    compiled search; the episodes must depend on neither: each group's are those of a plain play, one
    after another, with its own key and seed, through a program compiled apart. (The batch of the
    `episodes` fixture: a worker that ran it reuses its program.)"""
    from rllock.search.mcts import CompiledSearch, Searcher
    from rllock.search.network import PolicyValueNet

    assert group_sizes(5, 2) == [3, 2] and group_sizes(5, 9) == [1] * 5
    task = make_task("box:4x4x2", 3)
    net = NetConfig(canvas=4, features=(4, 8))
    shared = searchers(net, SMALL, ChunkStore, task, episodes=12, groups=2)
    assert [s.batch for s in shared] == [6, 6]
    assert shared[0].compiled is shared[1].compiled and shared[0].slot != shared[1].slot
    # Searchers made later in the process, for a task of the same shape, reuse the same program.
    again = Searcher(PolicyValueNet(net), SMALL, ChunkStore, make_task("box:4x4x2", 3), 6)
    assert again.compiled is shared[0].compiled and again.slot not in (shared[0].slot, shared[1].slot)
    assert searchers(net, SMALL, ChunkStore, task, 4, 1)[0].compiled is not shared[0].compiled  # batch 4
    apart = CompiledSearch(PolicyValueNet(net), SMALL, ChunkStore, task, 6)
    alone = [Searcher(PolicyValueNet(net), SMALL, ChunkStore, task, 6, apart) for _ in range(2)]
    assert apart is not shared[0].compiled
    params = init_params(net, jax.random.PRNGKey(0))
    key = jax.random.PRNGKey(4)
    together = play_groups(shared, params, task, key, seed=11)  # both groups in threads, at once
    one_by_one = [
        e
        for g, s in enumerate(alone)
        for e in s.play(params, task, jax.random.fold_in(key, g), seed=derive_seed(11, g), parallel=False)
    ]
    assert len(together) == len(one_by_one) == 12
    for a, b in zip(together, one_by_one):
        np.testing.assert_array_equal(a.labels, b.labels)
        np.testing.assert_array_equal(a.actions, b.actions)
        np.testing.assert_allclose(a.pi, b.pi)
    gc.collect()
    assert not shared[0].compiled.stores  # a play's node store goes with it, not with the shared program


def test_the_process_keeps_its_most_recently_used_searches_only():
    from rllock.search.mcts import SharedSearches

    shared = SharedSearches(limit=2)
    task, net = make_task("box:4x4x2", 4), NetConfig(canvas=4, features=(4, 8))
    first, second = (shared.get(net, SMALL, ChunkStore, task, b) for b in (1, 2))
    assert shared.get(net, SMALL, ChunkStore, make_task("box:4x4x2", 4), 1) is first  # the newest now
    shared.get(net, SMALL, ChunkStore, task, 3)
    assert shared.get(net, SMALL, ChunkStore, task, 1) is first
    assert shared.get(net, SMALL, ChunkStore, task, 2) is not second  # let go, made anew
