"""The voxel-level MDP against the frontier rules and the reference checkers."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import parts_after, reference_bits

from rllock.core import compiled_checkers as checkers
from rllock.core import reference_checkers as ref
from rllock.core.env import State, make_task
from rllock.core.voxel_env import initial_voxel_state, is_solved, is_terminal, legal_mask, step


def _frontier_rule(task, state) -> set[int]:
    """The legal voxels by the rules, on coordinates: remaining voxels face-touching the growing piece,
    or, for a new piece, the previous piece (any remaining voxel for the first)."""
    coords = [tuple(int(c) for c in xyz) for xyz in task.topology.coords]
    label = {coords[v]: int(state.labels[v]) for v in range(task.size)}
    remaining = [v for v in range(task.size) if state.labels[v] == 0]
    if state.failed or state.placed == task.pieces - 1:
        return set()
    if state.placed == 0 and state.filled == 0:
        return set(remaining)
    target = state.placed + 1 if state.filled else state.placed
    return {v for v in remaining if any(label.get(ref.shift(coords[v], d)) == target for d in ref.DIRECTIONS)}


def _walks(task, rng, episodes):
    """Random legal walks: every state visited, and each completed piece as (state before, chunk,
    accepted)."""
    for _ in range(episodes):
        state = initial_voxel_state(task)
        while not is_terminal(task, state):
            yield state, None
            legal = np.flatnonzero(legal_mask(task, state))
            nxt, reward = step(task, state, int(rng.choice(legal)))
            if nxt.placed > state.placed or nxt.failed:
                piece = state.placed + 1
                chunk = np.flatnonzero(nxt.labels == piece)
                before = State(
                    np.where(state.labels == piece, 0, state.labels).astype(np.int16), state.placed
                )
                yield state, (before, chunk, not nxt.failed, reward)
            state = nxt
        yield state, None


@pytest.mark.parametrize("shape,k,episodes", [("cube4", 7, 40), ("box:4x3x3", 6, 40), ("ring", 15, 25)])
def test_legal_masks_follow_the_frontier_rules(shape, k, episodes):
    task = make_task(shape, k)
    rng = np.random.default_rng(k)
    checked = 0
    for state, _ in _walks(task, rng, episodes):
        assert set(np.flatnonzero(legal_mask(task, state)).tolist()) == _frontier_rule(task, state)
        checked += 1
    assert checked > 300


@pytest.mark.parametrize("shape,k,removal", [("cube4", 7, "straight"), ("box:4x3x3", 6, "path")])
def test_a_completed_piece_is_accepted_exactly_when_the_reference_checkers_accept_it(shape, k, removal):
    task = make_task(shape, k, removal)
    rng = np.random.default_rng(3)
    outcomes = {True: 0, False: 0}
    for _ in range(8):
        for _, done in _walks(task, rng, 25):
            if done is None:
                continue
            before, chunk, accepted, reward = done
            parts, rest = parts_after(task, before, chunk)
            assert accepted == (reference_bits(parts, rest, removal) == checkers.ALL_CHECKS)
            assert reward == (1.0 / k if accepted else 0.0)
            outcomes[accepted] += 1
    assert outcomes[True] > 20 and outcomes[False] > 20


def test_an_episode_ends_solved_after_k_minus_1_accepted_pieces_with_return_one_minus_1_over_k():
    task = make_task("box:4x4x2", 3)
    rng = np.random.default_rng(0)
    for _ in range(200):
        state, total = initial_voxel_state(task), 0.0
        while not is_terminal(task, state):
            state, reward = step(task, state, int(rng.choice(np.flatnonzero(legal_mask(task, state)))))
            total += reward
        if is_solved(task, state):
            assert state.placed == 2 and total == pytest.approx(2 / 3) and not legal_mask(task, state).any()
            break
    else:
        pytest.fail("no random walk solved box:4x4x2 K=3")
    first, _ = step(task, initial_voxel_state(task), 0)
    far = int(np.argmax(np.abs(task.topology.coords - task.topology.coords[0]).sum(axis=1)))
    with pytest.raises(ValueError, match="not a legal action"):
        step(task, first, far)  # not touching the growing piece
