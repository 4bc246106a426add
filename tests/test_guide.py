"""The guide network and the search it guides: the plain search unchanged, the inputs against a simple
reference, the states the search reports and their rollout labels, guided assemblies verified, bad guide
checkpoints."""

from __future__ import annotations

import hashlib
import json
import re
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import jax
import numpy as np
import pytest
from helpers import run_cli

from rllock.actors.guide_actor import Probes, label_children, run_search, value_target
from rllock.config import GuideConfig, GuideTrainConfig, to_json
from rllock.core.env import State, apply_chunk, initial_state, make_task, sample_accepted
from rllock.core.feasibility import impossibility
from rllock.core.verifier import verify_labels
from rllock.errors import RLLockError
from rllock.files import orbax_io
from rllock.files.checkpoint import saved_steps
from rllock.learner.guide_learner import (
    SHARE,
    SIBLINGS_WITHIN,
    GuideBuffer,
    GuideLearner,
    held_out,
    judge,
    sibling_order,
    siblings,
)
from rllock.search.base import derive_seed
from rllock.search.curriculum import blob, draw_task, edge_pieces, named_tasks
from rllock.search.dfs import SearchStats, dfs, expand
from rllock.search.dives import RestartSequence, best_dive, dive_allowance
from rllock.search.guide import CHANNELS, GLOBALS, Guide, channels, encode, guide_values, init_guide
from rllock.search.guide_checkpoint import guide_metadata, load_guide, read_guide_metadata
from rllock.search.restarts import luby, rollout_reach
from rllock.search.search_config import SearchConfig
from rllock.search.solver import search, solve

CONFIG = GuideConfig(window=8, guide_features=(4, 8), guide_hidden=16)


def _untrained(seed: int = 0) -> Guide:
    return Guide(CONFIG, init_guide(CONFIG, jax.random.PRNGKey(seed)), f"untrained ({seed})")


def _plain_digest(config: SearchConfig) -> str:
    """Assemblies, node expansions and restarts of the plain search on fixed seeds, hashed."""
    digest = hashlib.sha256()
    for shape, k, removal, seed in [
        ("cube4", 7, "straight", 0),
        ("cube5", 13, "straight", 1),
        ("box:6x5x4", 12, "path", 2),
        ("desia-dog", 30, "straight", 0),
    ]:
        stats = SearchStats()
        task = make_task(shape, k, removal)
        for i, found in enumerate(search(task, seed=seed, time_limit=120, stats=stats, config=config)):
            digest.update(found.labels.astype(np.int16).tobytes())
            digest.update(str(found.expansions).encode())
            if i == 1:
                break
        digest.update(str((stats.expansions, stats.restarts)).encode())
    return digest.hexdigest()


def test_the_search_without_a_guide_is_the_solver_of_before_bit_for_bit():
    """Each former default stays there bit for bit, its digest recorded when it was the default: deep
    mode from K = 30 (commit 8fc97c6, before the guide existed), deep mode at every K with the smallest
    cuts (the commit after 63fd666), the remainder's surface under straight removal (6104197: the surface
    on the three straight tasks, the cut on the path task), each trying children by the lookahead's
    count; children in the order of the remainder's judgement on every task (measured beside them, as
    was `remainder="surface"` on every task); and the default (the commit after 24493fb): that order
    under straight removal, the count under path removal."""
    count = {"child_order": "count"}
    assert _plain_digest(SearchConfig(deep_from=30, remainder="cut", **count)) == (
        "b1bc94138f0585e14f9f8ebdea37be3dfe84b9ae04750554810ccda9b1498bed"
    )
    assert _plain_digest(SearchConfig(remainder="cut", **count)) == (
        "71ab68ab1bf577bb3efdbcf51a06f175b7312d22478e4218885f896d5f177039"
    )
    assert _plain_digest(SearchConfig(remainder="surface", **count)) == (
        "5a5edf98c1561c9d9d24935a82007a3b180f8b44cf558a437807c62471a0d468"
    )
    assert (
        _plain_digest(SearchConfig(**count))
        == "6e7dea6b029989af32131340ede9cd0723efd1a5ca1e370e29499bfd318b1776"
    )
    assert _plain_digest(SearchConfig(child_order="remainder")) == (
        "5d8d04da8f97adceedde999dad0cc2418f35d35ddfade9aae3a775f1d73cb102"
    )
    assert _plain_digest(SearchConfig()) == "efb8f3fb0dd480f6556c213ded3dc1f3b15073411ddc940ac713a07acdde0246"


def _reference_window(task, state, w):
    """Each window cell looked up one by one."""
    coords = task.topology.coords
    if state.placed:
        last = coords[state.labels == state.placed]
        centre = (last.min(axis=0) + last.max(axis=0)) / 2
    else:
        centre = (np.array(task.topology.dims) - 1) / 2
    lo = np.round(centre).astype(int) - w // 2
    label_at = {tuple(c): int(label) for c, label in zip(coords, state.labels)}
    out = np.zeros((w, w, w, CHANNELS), np.int8)
    for x in range(w):
        for y in range(w):
            for z in range(w):
                label = label_at.get((lo[0] + x, lo[1] + y, lo[2] + z))
                out[x, y, z] = [label == 0, label is not None and label > 0, label is None]
    return out


def test_the_window_matches_a_cell_by_cell_reference_and_features_are_bounded():
    rng = np.random.default_rng(3)
    for shape, k in [("bunny", 20), ("box:9x5x3", 9), ("desia-dog", 40)]:
        task = make_task(shape, k)
        state = initial_state(task)
        states = [state]
        for _ in range(5):
            chunks = sample_accepted(task, state, seed=int(rng.integers(1 << 30)), num_samples=256)
            if not len(chunks):
                break
            state = apply_chunk(state, chunks[0])
            states.append(state)
        encoded = encode(task, states, [1.0] * len(states), GuideConfig(window=8))
        assert encoded.window.shape == (len(states), 8, 8, 8, CHANNELS)
        assert encoded.features.shape == (len(states), GLOBALS)
        for i, s in enumerate(states):
            np.testing.assert_array_equal(encoded.window[i], _reference_window(task, s, 8))
        assert np.isfinite(encoded.features).all() and (encoded.features >= 0).all()
        remaining = encoded.features[:, 0]  # R's share of the shape falls with each piece
        assert (np.diff(remaining) < 0).all() and remaining[0] == 1.0


def _reference_overview(task, state, w):
    """Each voxel of R's bounding box put in its cell one by one."""
    coords = task.topology.coords
    free = coords[state.labels == 0]
    lo, hi = free.min(axis=0), free.max(axis=0) + 1
    step = max(1.0, max(hi - lo) / w)
    label_at = {tuple(c): int(label) for c, label in zip(coords, state.labels)}
    counts = np.zeros((w, w, w, 3))
    for x in range(lo[0], hi[0]):
        for y in range(lo[1], hi[1]):
            for z in range(lo[2], hi[2]):
                cell = tuple(int((v - a) / step) for v, a in zip((x, y, z), lo))
                label = label_at.get((x, y, z), -1)
                counts[cell] += [1, label == 0, label > 0]
    return np.round(100 * counts[..., 1:] / np.maximum(counts[..., :1], 1)).astype(np.int8)


def test_the_overview_matches_a_voxel_by_voxel_reference_and_feeds_the_network():
    rng = np.random.default_rng(4)
    config = GuideConfig(window=8, guide_features=(4, 8), guide_hidden=16, overview=True)
    for shape, k in [("bunny", 20), ("box:5x4x3", 6), ("desia-dog", 40)]:  # R's box above and below 8
        task = make_task(shape, k)
        state = initial_state(task)
        for _ in range(6):
            encoded = encode(task, [state], [1.0], config)
            assert encoded.window.shape == (1, 8, 8, 8, channels(config))
            window = encoded.window[0]
            np.testing.assert_array_equal(window[..., :CHANNELS], _reference_window(task, state, 8))
            np.testing.assert_array_equal(window[..., CHANNELS:], _reference_overview(task, state, 8))
            chunks = sample_accepted(task, state, seed=int(rng.integers(1 << 30)), num_samples=256)
            if not len(chunks):
                break
            state = apply_chunk(state, chunks[0])
    guide = Guide(config, init_guide(config, jax.random.PRNGKey(0)), "untrained, overview")
    values = guide.values(task, [initial_state(task), state], [1.0, 1.0])
    assert values.shape == (2,) and ((values > 0) & (values < 1)).all() and values[0] != values[1]


def test_the_search_reports_the_states_it_leaves_and_an_assemblys_path_whole():
    task = make_task("cube4", 7)
    left = []
    found = next(search(task, seed=0, time_limit=60, record=lambda s, share: left.append((s, share))))
    assert verify_labels(found.labels, task.removal).valid
    assert all(0 < share <= 1 for _, share in left)
    # The last states reported are the path to the assembly, the root first: each a prefix of it.
    path = left[-(task.pieces - 1) :]
    assert [s.placed for s, _ in path] == list(range(task.pieces - 1)) and path[0][1] == 1.0
    flat = found.labels[tuple(task.topology.coords.T)]
    for s, _ in path:
        placed = s.labels > 0
        np.testing.assert_array_equal(s.labels[placed], flat[placed])


def test_rollouts_tell_a_prefix_of_an_assembly_from_a_dead_end():
    task = make_task("cube4", 7)
    path = []
    next(search(task, seed=0, time_limit=60, record=lambda s, share: path.append(s)))
    prefix = path[-2]  # the assembly's path, one piece before its last placed piece
    assert rollout_reach(task, prefix, seed=0, expansions=400) == 1.0
    # A first piece that walls the cube in two: no piece can keep the rest connected, so no rollout wins.
    wall = np.where(task.topology.coords[:, 0] == 1, 1, 0).astype(np.int16)
    assert rollout_reach(task, State(wall, 1), seed=0, expansions=400) < 1.0


def test_a_rollouts_reach_is_the_share_of_the_pieces_left_it_placed():
    task = make_task("cube4", 7)
    path = []
    next(search(task, seed=0, time_limit=60, record=lambda s, share: path.append(s)))
    assert rollout_reach(task, path[-2], seed=0, expansions=400) == 1.0
    # One expansion samples the root's children (and their continuations, the lookahead): one piece of
    # the six to place.
    assert rollout_reach(task, initial_state(task), seed=0, expansions=1) == 1 / 6
    # sofa K=19 needs more than 300 expansions from its root: rollouts reach deeper the more they may expand,
    # since the same seed with a larger budget runs the smaller one's restarts first.
    sofa = make_task("sofa", 19)
    reach = [rollout_reach(sofa, initial_state(sofa), seed=0, expansions=e) for e in (1, 10, 100, 300)]
    assert all(0 < r < 1.0 and round(18 * r, 9).is_integer() for r in reach), reach
    assert reach == sorted(reach) and reach[0] == 1 / 18 and reach[-1] >= 0.5
    wall = State(np.where(task.topology.coords[:, 0] == 1, 1, 0).astype(np.int16), 1)
    assert rollout_reach(task, wall, seed=0, expansions=400) == 0.0  # the rest is in two parts already


def test_probes_label_children_as_the_search_makes_them_with_rollout_shares():
    # Rollouts this short on a tight cube: some win, some fail part of the way (on cube4 K=7 every
    # rollout of the search since the remainder's surface wins).
    task = make_task("cube4", 8)
    config = GuideTrainConfig(guide=CONFIG, rollouts=2, rollout_expansions=20)
    probes = Probes(task, 2, 1, 4, np.random.default_rng(0))
    next(search(task, seed=1, time_limit=60, record=probes))
    assert probes.seen >= 2 and len(probes.kept) == 2
    assert all(1 <= task.pieces - 1 - s.placed <= 4 for s in probes.kept)
    labelled = label_children(task, probes.kept, config, seed=3)
    children = sum(len(expand(task, s, seed=derive_seed(3, p))) for p, s in enumerate(probes.kept))
    assert len(labelled.target) == children == len(labelled.window) == len(labelled.features)
    first = len(expand(task, probes.kept[0], seed=derive_seed(3, 0)))
    assert labelled.group.tolist() == [0] * first + [1] * (children - first)
    assert set(np.unique(labelled.target)) <= {0.0, 0.5, 1.0} and labelled.target.max() == 1.0
    assert labelled.reach.shape == (children, 2) and ((labelled.reach >= 0) & (labelled.reach <= 1)).all()
    np.testing.assert_array_equal(labelled.target, (labelled.reach == 1.0).mean(axis=1))
    np.testing.assert_array_equal(value_target(labelled, "won"), labelled.target)
    reach = value_target(labelled, "reach")
    np.testing.assert_allclose(reach, labelled.reach.mean(axis=1))
    assert not np.array_equal(reach, labelled.target)  # some rollout failed part of the way
    again = label_children(task, probes.kept, config, seed=3)
    np.testing.assert_array_equal(labelled.target, again.target)


def test_labelling_skips_dead_ends_and_stops_at_the_probes_wanted():
    # A failing search leaves mostly dead ends: they are passed over, and the next kept states with
    # children are labelled instead, at most `probes` of them.
    task = make_task("cube4", 8)
    config = GuideTrainConfig(guide=CONFIG, rollouts=1, rollout_expansions=5, probes=2)
    dead = State(np.where(task.topology.coords[:, 0] == 1, 1, 0).astype(np.int16), 1)
    root = initial_state(task)
    assert expand(task, dead, seed=derive_seed(3, 0)) == []
    labelled = label_children(task, [dead, root, dead, root, root], config, seed=3)
    counts = [len(expand(task, root, seed=derive_seed(3, p))) for p in (1, 3)]
    assert min(counts) > 0
    assert labelled.group.tolist() == [1] * counts[0] + [3] * counts[1]


def test_an_actors_guided_search_dives_and_asks_the_guide_nothing_before_its_dives():
    # cube5 K=13 is solved by the first restart, which is the solver's: a diving search asks the guide
    # nothing, and labels what the unguided search labels.
    task = make_task("cube5", 13)
    config = GuideTrainConfig(guide=CONFIG, rollouts=1, rollout_expansions=5, probes=1, max_left=6)
    guide = _Counted(replace(_untrained(), horizon=6))
    guided, solved, placed, _ = run_search(config, 0, 0, guide, [task])  # type: ignore[arg-type]
    assert solved and placed == task.pieces - 1 and guide.calls == []
    np.testing.assert_array_equal(guided.window, run_search(config, 0, 0, None, [task])[0].window)


def _constant(value: float) -> Guide:
    """A guide that values every state `value` (its last layer's bias alone)."""
    params = dict(jax.tree.map(np.asarray, _untrained().params))
    logit = float(np.log(value / (1 - value)))
    params["Dense_2"] = {"kernel": np.zeros_like(params["Dense_2"]["kernel"]), "bias": np.full(1, logit)}
    return Guide(CONFIG, params, f"constant {value}")


def test_a_guide_that_keeps_the_search_order_searches_as_the_solver_does():
    task = make_task("cube5", 13)
    keep = SearchConfig()  # K = 13: no dive state 20 pieces before the end, so nothing for the guide
    runs = []
    for guide, config in ((None, SearchConfig()), (_constant(0.3), keep), (_untrained(), keep)):
        stats = SearchStats()
        found = next(search(task, seed=1, time_limit=120, guide=guide, config=config, stats=stats))
        runs.append((found.labels.tobytes(), found.expansions, stats.restarts))
    assert runs[0] == runs[1] == runs[2]


def test_a_restart_goes_on_from_the_best_valued_of_its_dives_and_those_left_before():
    task = make_task("cube5", 13)
    guide = replace(_untrained(3), horizon=5)
    config = SearchConfig(dives=4)
    stats, kept = SearchStats(), []
    deadline = time.monotonic() + 3600  # the budgets bound the dives; a loaded machine must not cut them
    rng = np.random.default_rng(7)
    begun = []
    for _ in range(3):
        begin, used = best_dive(
            task, rng, config, 10_000, deadline, stats, lambda: False, None, guide, None, kept
        )
        begun.append((begin, used))
    # The same dives again, one by one, from the same generator; each restart takes the best left.
    again, left = np.random.default_rng(7), []
    for begin, used in begun:
        spent = 0
        for _ in range(4):
            state, n = dfs(task, again, config, 10_000, deadline, 13 - 1 - 5, SearchStats())
            left += [] if state is None else [state]  # a dive can fail: the others still count
            spent += n
        values = guide.values(task, left, [1.0] * len(left))
        best = left.pop(int(np.argmax(values)))
        assert begin is not None and begin.placed == 7 and used == spent and len(np.unique(values)) > 1
        assert np.array_equal(begin.labels, best.labels)
    assert len(kept) == len(left)
    # One dive, or none within the horizon: the restart begins at the root, as the solver's does.
    for cfg, g in ((SearchConfig(dives=1), guide), (config, replace(guide, horizon=12)), (config, None)):
        assert best_dive(task, rng, cfg, 100, deadline, stats, lambda: False, None, g, None, []) == (None, 0)
    # In a search, assemblies found below a dive are whole and valid.
    for found in solve(task, count=3, time_limit=120, seed=4, guide=guide, config=config):
        assert verify_labels(found, task.removal).valid


def test_the_dives_share_grows_past_its_units_in_proportion_to_the_solvers_expansions():
    config, unit = SearchConfig(dive_share=0.5, dive_share_grows_after=4), 100
    allowed = [dive_allowance(config, unit, used) for used in (0, 200, 400, 800, 1600)]
    assert allowed == [0, 100, 200, 800, 3200]  # half, until 4 units; then half of used x used / 400
    assert dive_allowance(replace(config, dive_share=0), unit, 10**6) == 0


def test_a_diving_restart_is_planned_with_its_dives_as_they_took_so_far():
    sequence = RestartSequence(np.random.default_rng(0))
    assert sequence.planned(100, 40) == 100 + 40  # before any dive: one expansion a piece
    sequence.restarts, sequence.ran, sequence.dived = 2, 2, 3000
    assert sequence.planned(100, 40) == 100 * luby(3) + 1500


def test_the_solvers_restarts_go_on_beside_the_diving_ones_as_the_solvers():
    task = make_task("cube4", 9)
    guide, config = replace(_untrained(), horizon=3), SearchConfig(dive_share=0.5)
    unit = config.restart_unit(task, task.pieces - 1)
    theirs = 0
    for seed in range(10):
        plain = next(search(task, seed=seed, time_limit=60))
        stats = SearchStats()
        guided = next(search(task, seed=seed, time_limit=60, guide=guide, config=config, stats=stats))
        assert verify_labels(guided.labels, task.removal).valid
        dived = guided.expansions - plain.expansions
        if stats.dives == 0:  # solved before the first dive: the solver's search, node for node
            assert (guided.labels.tobytes(), dived) == (plain.labels.tobytes(), 0)
            continue
        # the diving restarts kept within their share, but for the last one's dives and its own budget
        last = (config.dives + 1) * unit * luby(stats.dives)
        assert dived <= dive_allowance(config, unit, plain.expansions) + last
        if np.array_equal(guided.labels, plain.labels):  # the solver's restarts found it, as the solver's did
            assert dived > 0
            theirs += 1
    assert theirs >= 2
    # No share, no dives: the solver's search, node for node.
    stats, never = SearchStats(), SearchConfig(dive_share=0)
    none = next(search(task, seed=0, time_limit=60, guide=guide, config=never, stats=stats))
    plain = next(search(task, seed=0, time_limit=60))
    assert (none.expansions, stats.dives) == (plain.expansions, 0)
    assert np.array_equal(none.labels, plain.labels)


class _Counted:
    """A guide that counts the states it is asked to value, call by call."""

    def __init__(self, guide: Guide):
        self.guide, self.horizon, self.calls = guide, guide.horizon, []

    def values(self, task, states, shares):
        self.calls.append(len(states))
        return self.guide.values(task, states, shares)


def _sixrestart_until(task, config: SearchConfig) -> tuple[list, SearchStats, list[int]]:
    """A search with an untrained guide (horizon 6) stopped as its sixth restart begins: the
    assemblies found, its stats and the sizes of its calls to the guide."""
    guide, stats = _Counted(replace(_untrained(), horizon=6)), SearchStats()
    runs = search(
        task, seed=2, time_limit=60, guide=guide, config=config, stats=stats, stop=lambda: stats.restarts > 5
    )  # type: ignore[arg-type]
    return list(runs), stats, guide.calls


def test_a_guide_that_keeps_the_order_and_dives_values_only_the_dive_states():
    task = make_task("desia-dog", 60)
    found, stats, calls = _sixrestart_until(task, SearchConfig(dives=3, dive_share=10.0))
    assert not found and stats.restarts == 6
    assert len(calls) == stats.dives >= 3 and max(calls) <= 3  # one call per diving restart


def test_the_curriculum_draws_feasible_varied_tasks():
    config = GuideTrainConfig(max_voxels=800)
    tasks = [draw_task(np.random.default_rng([5, i]), config) for i in range(12)]
    assert all(5 <= t.pieces <= config.max_pieces and t.piece_size >= 2 for t in tasks)
    assert {t.removal for t in tasks} == {"straight", "path"}
    assert not any(t.shape_name in ("mario", "spider") for t in tasks)
    grid = blob(np.random.default_rng(0), 300)
    from rllock.core.shapes import is_connected

    assert grid.sum() == 300 and is_connected(grid)


def test_named_cells_replace_the_curriculum_and_bad_ones_are_one_line_errors():
    named = named_tasks("cube4:9, desia-bunny:80:path")
    assert [(t.shape_name, t.pieces, t.removal) for t in named] == [
        ("cube4:9", 9, "straight"),
        ("desia-bunny:80:path", 80, "path"),
    ]
    config = GuideTrainConfig()
    drawn = {draw_task(np.random.default_rng([5, i]), config, named).shape_name for i in range(20)}
    assert drawn == {"cube4:9", "desia-bunny:80:path"}
    for spec, message in [
        ("", "--cells is empty"),
        ("cube4", "bad cell 'cube4'"),
        ("nosuchshape:9", "nosuchshape"),
        ("cube4:40", "cannot have a valid assembly"),
    ]:
        with pytest.raises(RLLockError, match=message) as error:
            named_tasks(spec)
        assert "\n" not in str(error.value)
    with pytest.raises(RLLockError, match="--max-learner-steps must be at least 1"):
        GuideTrainConfig(max_learner_steps=0).validate()
    with pytest.raises(RLLockError, match="--edge moves the K of the tasks in --cells"):
        GuideTrainConfig(edge=True).validate()


def test_edge_moves_a_cells_k_up_after_a_solve_and_down_after_a_failure_within_its_bounds():
    cube6, dog, mario = named_tasks("cube6:20,desia-dog:60,mario:60")  # N = 216, 581 and 548
    # To the next K up or down whose last piece is under twice the others: the next piece size.
    assert [edge_pieces(20, True, cube6), edge_pieces(20, False, cube6)] == [21, 19]
    assert [edge_pieces(60, True, mario), edge_pieces(68, False, mario)] == [68, 60]  # pieces of 8 and 9
    assert [edge_pieces(60, True, dog), edge_pieces(60, False, dog)] == [64, 58]
    assert [edge_pieces(120, True, dog), edge_pieces(120, False, dog)] == [145, 116]
    # Against the rule spelled out by brute force: the nearest K each way whose N mod K < N // K and that
    # no proof rules out (spider: K = 20-42 are impossible, docs/results.md).
    (spider,) = named_tasks("spider:15")
    for task in (cube6, dog, mario, spider):
        n_all = task.size
        tight = [
            j
            for j in range(task.pieces // 2, n_all // 4 + 1)
            if n_all % j < n_all // j and impossibility(replace(task, pieces=j)) is None
        ]
        for k in range(task.pieces // 2 + 1, n_all // 4):
            up = min((j for j in tight if j > k), default=k)
            down = max((j for j in tight if j < k), default=k)
            moved = (edge_pieces(k, True, task), edge_pieces(k, False, task))
            assert moved == (up, down), (task.shape_name, k)
    # Within [K/2, N/4]: pieces of at least 4 voxels, never under half the cell's K.
    assert edge_pieces(54, True, cube6) == 54 and edge_pieces(10, False, cube6) == 10
    assert edge_pieces(145, True, dog) == 145 and edge_pieces(30, False, dog) == 30
    # A long run of failures walks down to K/2 and stays; of solves, up to N/4.
    k = 20
    for _ in range(30):
        k = edge_pieces(k, False, cube6)
    assert k == 10
    for _ in range(60):
        k = edge_pieces(k, True, cube6)
    assert k == 54
    # A cell asked at pieces under 4 voxels keeps its K as the top; a K a proof rules out is not taken.
    (tiny,) = named_tasks("cube4:20")
    assert edge_pieces(20, True, tiny) == 20
    (flat,) = named_tasks("box:8x8x1:2")
    assert edge_pieces(2, True, flat) == 2  # a slab one voxel thick has assemblies only at K = 2
    assert edge_pieces(19, True, spider) == 19  # K = 20-52: none open whose last piece is under 2n
    # The drawn task is the cell's at the K given for its label.
    config = GuideTrainConfig(cells="cube6:20,desia-dog:60", edge=True)
    drawn = {
        (t.shape_name, t.pieces)
        for t in (
            draw_task(np.random.default_rng([5, i]), config, [cube6, dog], {"cube6:20": 23})
            for i in range(20)
        )
    }
    assert drawn == {("cube6:20", 23), ("desia-dog:60", 60)}


def test_the_guide_learner_fits_the_buffers_targets_and_orders_siblings():
    buffer = GuideBuffer(64, 8)
    rng = np.random.default_rng(0)
    window = rng.integers(0, 2, size=(64, 8, 8, 8, CHANNELS)).astype(np.int8)
    features = rng.random((64, GLOBALS)).astype(np.float32)
    # A node's level (feature 0, shared by its 4 children) sets most of a target; feature 1 orders them.
    group = np.repeat(np.arange(16), 4)
    features[:, 0] = features[group * 4, 0]
    target = (0.8 * (features[:, 0] > 0.5) + 0.2 * features[:, 1]).astype(np.float32)
    counts = buffer.add(window, features, target, group)
    assert counts.size == 64 and counts.added == 64
    learner = GuideLearner(CONFIG, 3e-3, jax.random.PRNGKey(0), rank_weight=1.0)
    batch = buffer.sample(128, 0)
    assert batch["paired"].all() and len(batch["target"]) == 128
    first = learner.update(batch)
    for _ in range(80):
        last = learner.update(batch)
    assert last[0] < 0.7 * first[0] and last[1] < 0.7 * first[1]


def test_averaged_weights_are_the_guide_a_checkpoint_keeps_and_a_resume_restores_both(tmp_path):
    rng = np.random.default_rng(2)
    batch = {
        "window": rng.integers(0, 2, size=(16, 8, 8, 8, CHANNELS)).astype(np.int8),
        "features": rng.random((16, GLOBALS)).astype(np.float32),
        "target": rng.random(16).astype(np.float32),
        "paired": np.zeros(8, bool),
    }
    decay = 0.75
    averaged = GuideLearner(CONFIG, 1e-2, jax.random.PRNGKey(3), weight_average=decay)
    plain = GuideLearner(CONFIG, 1e-2, jax.random.PRNGKey(3))
    assert plain.guide is plain.params
    # A plain running average over each step's weights, from the initial ones.
    want = [np.asarray(w, np.float64) for w in jax.tree.leaves(averaged.params)]
    for _ in range(5):
        averaged.update(batch)
        plain.update(batch)
        stepped = jax.tree.leaves(averaged.params)
        want = [decay * a + (1 - decay) * np.asarray(p) for a, p in zip(want, stepped)]
    for a, w in zip(jax.tree.leaves(averaged.guide), want):
        np.testing.assert_allclose(a, w, rtol=1e-5, atol=1e-6)
    # The learner itself steps as without averaging; the guide is not its last weights.
    for a, b in zip(jax.tree.leaves(averaged.params), jax.tree.leaves(plain.params)):
        np.testing.assert_array_equal(a, b)
    last = jax.tree.leaves(plain.params)
    assert not all(np.allclose(a, b) for a, b in zip(jax.tree.leaves(averaged.guide), last))
    config = GuideTrainConfig(guide=CONFIG, weight_average=decay)
    _save_guide(tmp_path / "run", averaged, config)
    for a, b in zip(jax.tree.leaves(load_guide(tmp_path / "run").params), jax.tree.leaves(averaged.guide)):
        np.testing.assert_array_equal(a, b)
    resumed = GuideLearner(CONFIG, 1e-2, jax.random.PRNGKey(9), weight_average=decay)
    step_dir = tmp_path / "run" / "checkpoints" / str(averaged.step)
    resumed.load_state(orbax_io.restore_like(step_dir, resumed.state()))
    averaged.update(batch)
    resumed.update(batch)
    for a, b in zip(jax.tree.leaves(resumed.state()), jax.tree.leaves(averaged.state())):
        np.testing.assert_allclose(a, b, rtol=1e-6)
    with pytest.raises(RLLockError, match="--weight-average"):
        replace(config, weight_average=1.0).validate()


def test_sibling_pairs_are_drawn_from_the_ring_as_a_brute_force_search_finds_them():
    rng = np.random.default_rng(1)
    buffer = GuideBuffer(50, 4)
    # Each push: a few nodes' children one after another, 1 to 8 of them (a node's most).
    pushes = [np.repeat(np.arange(k), rng.integers(1, 9, size=k)) for k in rng.integers(1, 4, size=12)]
    for local in pushes:
        n = len(local)
        buffer.add(np.zeros((n, 4, 4, 4, CHANNELS), np.int8), np.zeros((n, GLOBALS), np.float32),
                   rng.random(n).astype(np.float32), local)  # fmt: skip
    assert buffer.size == 50 and buffer.added == sum(len(p) for p in pushes) > 50
    group = buffer.group
    drawn: dict[int, set[int]] = {a: set() for a in range(50)}
    for seed in range(300):
        first = np.random.default_rng(seed).integers(0, 50, size=25)
        second, paired = siblings(group, first, np.random.default_rng(seed + 1000))
        for a, b, ok in zip(first.tolist(), second.tolist(), paired.tolist()):
            assert ok == (b != a) and (group[b] == group[a])
            drawn[a].add(b)
    # Brute force: a state's siblings are the other states of its push's node, less those overwritten
    # (and those across the ring's end from it, which the draw does not look for).
    for a in range(50):
        mates = {j for j in range(50) if j != a and group[j] == group[a] and abs(j - a) < SIBLINGS_WITHIN}
        assert drawn[a] == (mates or {a}), a


def _brute_sibling_order(score, target, group, gap: float = 0.0) -> tuple[float, int]:
    right = pairs = 0.0
    for i in range(len(target)):
        for j in range(len(target)):
            if group[i] == group[j] and target[i] - target[j] > gap:
                pairs += 1
                right += 1.0 if score[i] > score[j] else 0.5 if score[i] == score[j] else 0.0
    return (right / pairs if pairs else 0.5), int(pairs)


def test_held_out_nodes_are_never_trained_on_and_are_judged_as_a_brute_force_count_finds():
    rng = np.random.default_rng(4)
    buffer = GuideBuffer(400, 8)
    sizes = rng.integers(1, 9, size=40)
    local = np.repeat(np.arange(40), sizes)
    n = len(local)
    features = rng.random((n, GLOBALS)).astype(np.float32)
    features[: n // 2, SHARE] = np.round(features[: n // 2, SHARE], 1)  # ties
    target = np.round(rng.random(n), 1).astype(np.float32)
    window = rng.integers(0, 2, size=(n, 8, 8, 8, CHANNELS)).astype(np.int8)
    buffer.add(window, features, target, local)
    group = buffer.group[:n]
    for seed in range(50):
        batch = buffer.sample(32, seed)
        drawn = [np.flatnonzero((features == row).all(axis=1))[0] for row in batch["features"]]
        assert not held_out(group[drawn]).any()
    for kept_out, most in ((True, 100), (False, 7)):
        nodes = buffer.nodes(kept_out, most, 0)
        chosen = np.unique(nodes["group"])
        available = np.unique(group[held_out(group) == kept_out])
        assert (held_out(chosen) == kept_out).all() and len(chosen) == min(most, len(available))
        assert len(nodes["target"]) == np.isin(group, chosen).sum()  # every sibling of a chosen node
    nodes = buffer.nodes(False, 40, 0)
    params = init_guide(CONFIG, jax.random.PRNGKey(5))
    found = judge(params, CONFIG, nodes)
    values = np.asarray(guide_values(params, nodes["window"], nodes["features"], config=CONFIG))
    right, pairs = _brute_sibling_order(values, nodes["target"], nodes["group"])
    assert found["siblings"] == pytest.approx(right, abs=1e-9) and found["pairs"] == pairs > 50
    share = _brute_sibling_order(nodes["features"][:, SHARE], nodes["target"], nodes["group"])[0]
    assert found["share"] == pytest.approx(share, abs=1e-9)
    # The search's own order: the order the actor pushed a node's children in, best last.
    order = _brute_sibling_order(nodes["order"].astype(float), nodes["target"], nodes["group"])[0]
    assert found["search_order"] == pytest.approx(order, abs=1e-9)
    # Past the ring's end, the order is still the order they came in.
    ring = GuideBuffer(10, 8)
    for part in (np.arange(6), np.arange(6, 14)):
        came = np.zeros((len(part), GLOBALS), np.float32)
        came[:, 0] = part
        ring.add(window[: len(part)], came, target[: len(part)], part // 4 - part[0] // 4)
    both = [ring.nodes(kept_out, 10, 0) for kept_out in (True, False)]
    came = np.concatenate([b["features"][:, 0] for b in both])
    order = np.concatenate([b["order"] for b in both])
    assert sorted(came) == list(range(4, 14)) and (np.argsort(order) == np.argsort(came)).all()
    assert found["value_error"] == pytest.approx(np.abs(values - nodes["target"]).mean(), rel=1e-5)
    for trial in range(40):
        r = np.random.default_rng(trial)
        size, gap = int(r.integers(1, 40)), float(r.choice([0.0, 0.2]))
        score, tgt, grp = np.round(r.random(size), 1), np.round(r.random(size), 1), r.integers(0, 5, size)
        expected = _brute_sibling_order(score, tgt, grp, gap)
        assert sibling_order(score, tgt, grp, gap) == pytest.approx(expected), trial


def test_the_sibling_loss_matches_a_direct_computation():
    from rllock.learner.guide_learner import guide_losses

    params = init_guide(CONFIG, jax.random.PRNGKey(3))
    rng = np.random.default_rng(3)
    window = rng.integers(0, 2, size=(8, 8, 8, 8, CHANNELS)).astype(np.float32)
    features = rng.random((8, GLOBALS)).astype(np.float32)
    target = np.array([0.2, 0.5, 0.5, 1.0, 0.7, 0.1, 0.5, 0.0], np.float32)
    paired = np.array([True, True, False, True])
    value, rank = guide_losses(params, CONFIG, window, features, target, paired)
    from rllock.search.guide import GuideNet

    logits = np.asarray(GuideNet(CONFIG).apply({"params": params}, window, features), np.float64)

    def bce(x, y):
        return np.log1p(np.exp(-abs(x))) + max(x, 0) - x * y

    assert float(value) == pytest.approx(np.mean([bce(x, y) for x, y in zip(logits, target)]), rel=1e-4)
    # Pairs (0, 4), (1, 5), (3, 7): pair 2 is not siblings, and no pair has equal targets here.
    pairs = [(0, 4, 0.0), (1, 5, 1.0), (3, 7, 1.0)]
    expected = np.mean([bce(logits[i] - logits[j], y) for i, j, y in pairs])
    assert float(rank) == pytest.approx(expected, rel=1e-4)
    _, none = guide_losses(params, CONFIG, window, features, target, np.zeros(4, bool))
    assert float(none) == 0.0


def test_a_replay_snapshot_keeps_the_sibling_groups_and_an_older_one_pairs_nothing(tmp_path):
    buffer = GuideBuffer(16, 4)
    for local in (np.array([0, 0, 1, 1, 1]), np.array([0, 0, 0])):
        n = len(local)
        buffer.add(np.ones((n, 4, 4, 4, CHANNELS), np.int8), np.ones((n, GLOBALS), np.float32),
                   np.linspace(0, 1, n, dtype=np.float32), local)  # fmt: skip
    assert buffer.group[:8].tolist() == [0, 0, 1, 1, 1, 2, 2, 2]
    path = str(tmp_path / "replay.npz")
    buffer.snapshot(path)
    again = GuideBuffer(16, 4)
    assert again.restore(path) == 8
    np.testing.assert_array_equal(again.group[:8], buffer.group[:8])
    again.add(np.zeros((2, 4, 4, 4, CHANNELS), np.int8), np.zeros((2, GLOBALS), np.float32),
              np.zeros(2, np.float32), np.array([0, 0]))  # fmt: skip
    assert again.group[8:10].tolist() == [3, 3]  # numbered after the restored groups
    with np.load(path) as data:
        older = {k: data[k] for k in data.files if k not in ("group", "groups")}
    np.savez(tmp_path / "old.npz", **older)
    old = GuideBuffer(16, 4)
    old.restore(str(tmp_path / "old.npz"))
    assert not old.sample(8, 0)["paired"].any()


def _snapshot(path, seed: int, nodes: int) -> GuideBuffer:
    """A replay snapshot at `path` of `nodes` nodes of 3 children each, their targets a function of the
    features (so a network can fit them)."""
    rng = np.random.default_rng(seed)
    n = 3 * nodes
    features = rng.random((n, GLOBALS)).astype(np.float32)
    buffer = GuideBuffer(n, 8)
    buffer.add(rng.integers(0, 2, size=(n, 8, 8, 8, CHANNELS)).astype(np.int8), features,
               (0.7 * features[:, 0] + 0.3 * features[:, 1]).astype(np.float32),
               np.repeat(np.arange(nodes), 3))  # fmt: skip
    path.parent.mkdir(parents=True, exist_ok=True)
    buffer.snapshot(str(path))
    return buffer


def test_a_guide_trained_on_pooled_snapshots_is_the_learner_on_their_states_and_resumes(tmp_path):
    """train-guide --replay-from: every state of a run's snapshot and a snapshot file in one buffer,
    each's siblings apart; the checkpoint is the learner's steps on it, bit for bit, through a resume."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from rllock.orchestration.guide_offline import keep_snapshot, load_pool
    from rllock.orchestration.guide_train import train_guide

    a = _snapshot(tmp_path / "run-a" / "replay.npz", 1, 20)
    made = {"command": f"rllock train-guide --logdir {tmp_path}/run-a", "commit": "abc", "date": "today"}
    mngr = orbax_io.manager(tmp_path / "run-a" / "checkpoints", keep=1)
    learner = GuideLearner(CONFIG, 1e-3, jax.random.PRNGKey(0))
    orbax_io.save(mngr, 1, learner.state(), guide_metadata(GuideTrainConfig(guide=CONFIG), 1, {}, [made]))
    mngr.close()
    # The snapshot kept apart from its run: compressed, with the run's sessions beside it, portable.
    kept = keep_snapshot(tmp_path / "run-a", tmp_path / "kept" / "a.npz")
    assert kept["states"] == 60 and kept["sessions"][0]["command"] == "rllock train-guide --logdir run-a"
    assert (tmp_path / "kept" / "a.npz").stat().st_size < (tmp_path / "run-a" / "replay.npz").stat().st_size
    b = _snapshot(tmp_path / "b.npz", 2, 14)
    out = tmp_path / "offline"
    sources = f"{tmp_path / 'kept' / 'a.npz'},{tmp_path / 'b.npz'}"
    config = GuideTrainConfig(guide=CONFIG, logdir=str(out), replay_from=sources, batch_size=16,
                              max_learner_steps=30, minutes=3, checkpoint_minutes=10)  # fmt: skip
    pooled, _ = load_pool(config)
    assert pooled.size == 102
    np.testing.assert_array_equal(pooled.window[:102], np.concatenate([a.window, b.window]))
    np.testing.assert_array_equal(pooled.target[:102], np.concatenate([a.target, b.target]))
    # Nodes keep their children together and no node spans two snapshots.
    assert pooled.group[:102].tolist() == np.repeat(np.arange(34), 3).tolist()
    result = train_guide(config)
    assert result.steps == 30 and not result.interrupted
    reference = GuideLearner(CONFIG, config.guide_learning_rate, jax.random.PRNGKey(config.seed))
    for _ in range(30):
        reference.update(pooled.sample(16, reference.next_seed()))
    for got, want in zip(jax.tree.leaves(load_guide(out).params), jax.tree.leaves(reference.params)):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    doc = read_guide_metadata(out / "checkpoints" / "30")
    assert [r["states"] for r in doc["replay"]] == [60, 42]
    assert doc["replay"][0]["made_by"] == kept["sessions"] and doc["replay"][1]["made_by"] == []
    # The run's own folder names the same states.
    assert load_pool(replace(config, replay_from=str(tmp_path / "run-a")))[1][0]["made_by"] == [made]
    assert doc["replay"][1]["sha256"] == hashlib.sha256((tmp_path / "b.npz").read_bytes()).hexdigest()
    assert doc["counters"]["states"] == 102 and doc["config"]["replay_from"] == config.replay_from
    events = EventAccumulator(str(out))
    events.Reload()
    assert {"losses/value", "losses/siblings", "heldout/siblings", "trained/siblings"} <= set(
        events.Tags()["scalars"]
    )
    # A resume goes on with the optimizer state and the sampling key: the same as 40 steps in one go.
    result = train_guide(replace(config, max_learner_steps=40), resume=True)
    assert result.steps == 40
    for _ in range(10):
        reference.update(pooled.sample(16, reference.next_seed()))
    for got, want in zip(jax.tree.leaves(load_guide(out).params), jax.tree.leaves(reference.params)):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    assert len(read_guide_metadata(out / "checkpoints" / "40")["sessions"]) == 2
    with pytest.raises(RLLockError, match="already holds a guide run"):
        train_guide(config)
    _snapshot(tmp_path / "b.npz", 3, 14)
    with pytest.raises(RLLockError, match="not the ones it was trained on"):
        train_guide(replace(config, max_learner_steps=50), resume=True)


def test_train_guide_on_snapshots_stops_on_sigterm_with_a_checkpoint_and_resumes_from_it(tmp_path):
    """SIGTERM (a scheduler, `kill`) stops `train-guide --replay-from` as Ctrl-C does: a checkpoint at
    the signal past the periodic ones, the resume command, exit 128 + 15; the resume goes on from it."""
    _snapshot(tmp_path / "a.npz", 1, 40)
    out = tmp_path / "run"
    saved = out / "checkpoints"
    flags = ["--batch-size", "16", "--checkpoint-minutes", "0.05", "--logdir", str(out)]
    cli = [sys.executable, "-m", "rllock.orchestration.cli", "train-guide"]
    proc = subprocess.Popen([*cli, "--replay-from", str(tmp_path / "a.npz"), "--minutes", "5", *flags],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)  # fmt: skip
    try:
        end = time.monotonic() + 120
        while not saved_steps(saved):  # a periodic checkpoint: the loop runs, the handlers are in place
            assert proc.poll() is None and time.monotonic() < end, proc.communicate()[0]
            time.sleep(0.5)
        periodic = saved_steps(saved)[-1]
        time.sleep(1)
        proc.send_signal(signal.SIGTERM)
        text, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 143, text
    assert "SIGTERM: saving a checkpoint" in text and "Traceback" not in text
    assert f"rllock train-guide --resume {out}" in text
    stopped = saved_steps(saved)[-1]
    assert stopped > periodic
    code, _, err = run_cli("train-guide", "--resume", str(out), "--max-learner-steps", str(stopped + 5))
    assert code == 0, err
    assert f"resuming {out} at learner step {stopped}" in err and saved_steps(saved)[-1] == stopped + 5


def test_train_guide_on_snapshots_refuses_bad_ones_in_one_line(tmp_path):
    _snapshot(tmp_path / "ok.npz", 1, 4)
    (tmp_path / "broken.npz").write_bytes(b"PK not a zip")
    (tmp_path / "run").mkdir()
    cases = [
        ([str(tmp_path / "missing.npz")], "no replay snapshot there"),
        ([str(tmp_path / "run")], "no replay snapshot there"),
        ([str(tmp_path / "broken.npz")], "is missing or damaged"),
        ([str(tmp_path / "ok.npz"), "--window", "12"], "made with"),
    ]
    for args, message in cases:
        code, out, err = run_cli(
            "train-guide",
            "--replay-from",
            *args,
            "--logdir",
            str(tmp_path / "out"),
            "--max-learner-steps",
            "2",
        )
        assert code == 2 and message in err and len(err.strip().splitlines()) == 1, (args, err)
        assert not (tmp_path / "out" / "checkpoints").exists()


def _save_guide(folder, learner: GuideLearner, config: GuideTrainConfig):
    mngr = orbax_io.manager(folder / "checkpoints", keep=1)
    orbax_io.save(mngr, learner.step, learner.state(), guide_metadata(config, learner.step, {}, []))
    mngr.close()


def test_a_saved_guide_loads_with_its_weights_and_bad_ones_are_one_line_errors(tmp_path):
    config = GuideTrainConfig(guide=CONFIG)
    learner = GuideLearner(CONFIG, 1e-3, jax.random.PRNGKey(4))
    _save_guide(tmp_path / "run", learner, config)
    guide = load_guide(tmp_path / "run")
    assert guide.config == CONFIG
    for a, b in zip(jax.tree.leaves(guide.params), jax.tree.leaves(learner.params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(RLLockError, match="policy checkpoint"):
        load_guide("cube4-k7")
    with pytest.raises(RLLockError, match="no such checkpoint"):
        load_guide(tmp_path / "missing")
    step_dir = next((tmp_path / "run" / "checkpoints").iterdir())
    broken = tmp_path / "broken"
    shutil.copytree(step_dir, broken)
    (broken / "meta" / "metadata").write_text("{not json")
    with pytest.raises(RLLockError, match="corrupted or unreadable"):
        load_guide(broken)
    damaged = tmp_path / "damaged"
    shutil.copytree(step_dir, damaged)
    for f in (damaged / "state").rglob("*"):
        if f.is_file() and f.parent.name == "d":
            f.write_bytes(b"\0" * 7)
    with pytest.raises(RLLockError, match="corrupted or unreadable"):
        load_guide(damaged)


@pytest.mark.parametrize("guide", ["cube4-k7", "nowhere/run"])
def test_solve_with_a_bad_guide_is_one_line_and_exit_2_before_any_search(tmp_path, guide):
    code, _, err = run_cli(
        "solve", "--shape", "cube4", "--pieces", "7", "--guide", guide, "--out", str(tmp_path / "o")
    )
    assert code == 2 and err.count("\n") == 1, err
    assert not (tmp_path / "o").exists()


def test_solve_with_a_guide_writes_a_verified_assembly_that_names_it(tmp_path):
    config = GuideTrainConfig(guide=CONFIG)
    _save_guide(tmp_path / "run", GuideLearner(CONFIG, 1e-3, jax.random.PRNGKey(1)), config)
    code, out, err = run_cli(
        "solve",
        "--shape",
        "cube4",
        "--pieces",
        "7",
        "--guide",
        str(tmp_path / "run"),
        "--out",
        str(tmp_path / "o"),
    )
    assert code == 0, err
    doc = json.loads((tmp_path / "o" / "assembly_001" / "assembly.json").read_text())
    assert "run/checkpoints" in doc["method"]["guide"]
    assert to_json(config)["guide"]["window"] == 8
    assert "K=7 leaves no state 20 pieces before the end to dive to" in err  # the user is told


def test_bench_guide_runs_its_arms_on_the_same_seeds_and_refuses_bad_cells_in_one_line(tmp_path):
    config = GuideTrainConfig(guide=CONFIG)
    _save_guide(tmp_path / "run", GuideLearner(CONFIG, 1e-3, jax.random.PRNGKey(2)), config)
    bench = ["bench", "guide", "--guide", str(tmp_path / "run"), "--seeds", "0,1", "--time-limit", "30"]
    code, out, err = run_cli(*bench, "--cells", "cube4:6", "--dives", "2", "--untrained-seed", "3", "--json")
    assert code == 0, err
    doc = json.loads(out)
    (row,) = doc["rows"]
    assert doc["time_limit_s"] == 30 and row["cell"] == "cube4:6" and row["voxels"] == 64
    assert doc["untrained_seed"] == 3  # untrained networks of different seeds differ: the output says which
    # Every arm ran each seed once and solved it (cube4 K=6 takes the solver a fraction of a second).
    for arm in ("solver", "guided", "untrained"):
        assert len(row[arm]) == 2 and all(r["seconds"] is not None for r in row[arm]), row
    for bad, words in (("cube4", "bad cell"), ("cube4:x", "bad cell"), ("nosuchshape:6", "nosuchshape")):
        code, out, err = run_cli(*bench, "--cells", bad)
        assert code == 2 and err.count("\n") == 1 and words in err, err
    code, out, err = run_cli(*bench, "--cells", "cube4:6", "--dives", "0")
    assert code == 2 and err.count("\n") == 1 and "--dives must be at least 1" in err, err
    code, out, err = run_cli(*bench, "--cells", "cube4:6", "--untrained-seed", "-1")
    assert code == 2 and err.count("\n") == 1 and "--untrained-seed must be at least 0" in err, err


def test_the_guide_table_names_the_untrained_arms_seed():
    from rllock.orchestration.bench.guide import GuideRow, format_guide_table
    from rllock.orchestration.bench.shapes import Cell
    from rllock.search.curriculum import parse_named_task

    guide = Guide(CONFIG, init_guide(CONFIG, jax.random.PRNGKey(7)), "trained", horizon=9)
    arms = {"guided": [Cell(2.0, 30.0)], "untrained": [Cell(None, 30.0, placed=5)]}
    rows = [GuideRow(parse_named_task("cube4:6"), 64, arms)]
    table = format_guide_table(
        rows, ["guided", "untrained"], guide, "rllock bench guide", 30.0, untrained_seed=4
    )
    assert "| cell | N | guided (s per seed; median) | untrained, seed 4 (s per seed; median) |" in table
    assert "| cube4:6 | 64 | 2.0; 2.0 | none in 30 (best 5/5); 30.0 | - |" in table


def test_untrained_arms_of_other_seeds_are_other_initial_networks():
    from rllock.search.guide import untrained_like

    trained = Guide(CONFIG, init_guide(CONFIG, jax.random.PRNGKey(7)), "trained", horizon=9)
    task = make_task("cube4", 6)
    states = [initial_state(task)]
    arms = [untrained_like(trained, seed) for seed in (0, 1)]
    for seed, arm in enumerate(arms):
        assert arm.horizon == 9 and arm.source == f"untrained (seed {seed})"
        for a, b in zip(jax.tree.leaves(arm.params), jax.tree.leaves(_untrained(seed).params)):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    values = [arm.values(task, states, [1.0]) for arm in arms]
    assert not np.allclose(values[0], values[1])


def test_every_shipped_guide_loads_and_names_what_made_it_down_to_its_kept_data():
    """`--guide` alone loads the shipped guide; a guide trained on kept snapshots names them by hash,
    and they are the files in data/replay (so its command reproduces it from the repository)."""
    from rllock.orchestration.guide_offline import sha256
    from rllock.search.guide_checkpoint import SHIPPED_GUIDE, describe_guide, shipped_guides

    root = Path(__file__).resolve().parents[1]
    for name in shipped_guides():
        guide, row = load_guide(name), describe_guide(name)
        assert guide.config.window == row["window"] and row["learner_steps"] > 0, name
        assert row["command"].startswith("rllock train-guide") and row["commit"] and row["date"], name
        for kept in row["replay"]:
            assert sha256(root / kept["source"]) == kept["sha256"], kept["source"]
            assert kept["made_by"] and kept["made_by"][0]["command"].startswith("rllock train-guide")
    assert SHIPPED_GUIDE in shipped_guides()


def test_a_shipped_guide_names_no_machine_path_and_loads(tmp_path, monkeypatch, capsys):
    from test_shipped_files import machine_paths

    from rllock.search.guide_checkpoint import ship_guide
    from rllock.search.pretrained import COMMIT_SUCCESS

    monkeypatch.setattr(
        "sys.argv", [f"{tmp_path}/venv/bin/rllock", "train-guide", "--logdir", str(tmp_path / "run")]
    )
    learner = GuideLearner(CONFIG, 1e-3, jax.random.PRNGKey(2))
    config = GuideTrainConfig(guide=CONFIG, logdir=str(tmp_path / "run"))
    from rllock.files.provenance import provenance

    mngr = orbax_io.manager(tmp_path / "run" / "checkpoints", keep=1)
    orbax_io.save(mngr, 3, learner.state(), guide_metadata(config, 3, {"searches": 9}, [provenance()]))
    mngr.close()
    target = ship_guide(tmp_path / "run", "myguide", into=tmp_path / "guides")
    for path in (target / "meta" / "metadata", target / "state" / COMMIT_SUCCESS):
        assert str(tmp_path) not in path.read_text() and not machine_paths(path.read_bytes()), path
    doc = json.loads((target / "meta" / "metadata").read_text())
    assert doc["shipped"]["name"] == "myguide" and doc["sessions"][0]["command"].startswith(
        "rllock train-guide"
    )
    shipped = load_guide(target)
    for a, b in zip(jax.tree.leaves(shipped.params), jax.tree.leaves(learner.params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # `rllock pretrained` lists it below the policies, with what made it.
    monkeypatch.setattr("rllock.search.guide_checkpoint.GUIDES", tmp_path / "guides")
    from rllock.orchestration.cli.main import main

    assert main(["pretrained"]) == 0
    row = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("| myguide |"))
    assert "| 9 searches | 3 |" in row and "`rllock train-guide --logdir run`" in row, row


@pytest.mark.slow
@pytest.mark.ray
def test_train_guide_learns_on_ray_writes_checkpoints_and_events_and_resumes(tmp_path):
    """The command as a user runs it: search actors on Ray, the replay buffer actor, the learner,
    orbax checkpoints and TensorBoard events; --resume continues the step count and the buffer."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run = tmp_path / "run"
    # The curriculum of two named tasks (`--cells`), which the resumed run keeps, each at its edge of
    # failure (`--edge`: its K moves with the outcome of each of its searches).
    small = ["--search-seconds", "2", "--batch-size", "16", "--buffer-capacity", "4000", "--actors", "1",
             "--cells", "cube4:7,cube5:12", "--edge", "--guide-features", "4,8", "--guide-hidden", "16",
             "--publish-every", "5", "--checkpoint-minutes", "0.2",
             # One cheap rollout per child: the first labels reach the learner within its 36 s on a slow,
             # loaded VM too (three rollouts of 512 expansions each did not, once).
             "--probes", "1", "--rollouts", "1", "--rollout-expansions", "128",
             # No cap on learning from what was searched: the resumed run learns from its restored buffer
             # at once, not only after a new search, which a loaded machine may not finish in its 30 s.
             "--replay-ratio", "100000"]  # fmt: skip
    # It ends on its step limit (a few seconds of learning here); the minutes are only a ceiling: on a slow
    # VM under the rest of the suite, Ray's start and the learner's compilation took most of 0.6 minutes.
    code, out, err = run_cli(
        "train-guide", "--minutes", "3", "--max-learner-steps", "100", "--logdir", str(run), *small,
        timeout=300,
    )  # fmt: skip
    assert code == 0, err
    searched = set(re.findall(r"search \d+ \((\S+) K=", err))
    assert searched and searched <= {"cube4:7", "cube5:12"}, searched
    # One actor: each search of a cell is at the K its previous search left (`edge_pieces`).
    cells = {task.shape_name: task for task in named_tasks("cube4:7,cube5:12")}
    edge = {"cube4:7": 7, "cube5:12": 12}
    for cell, pieces, outcome in re.findall(r"search \d+ \((\S+) K=(\d+) straight, \w+\): (solved|not)", err):
        assert int(pieces) == edge[cell], (cell, pieces, edge, err)
        edge[cell] = edge_pieces(int(pieces), outcome == "solved", cells[cell])
    assert edge != {"cube4:7": 7, "cube5:12": 12}, err
    # The final checkpoint is skipped when the last periodic one already holds the same step and searches.
    saved = re.findall(r"checkpoint at learner step \d+ \(\d+ searches", err)
    assert saved and len(saved) == len(set(saved)), saved
    steps = sorted(int(p.name) for p in (run / "checkpoints").iterdir() if p.name.isdigit())
    assert steps and steps[-1] == 100 and (run / "replay.npz").exists()
    events = EventAccumulator(str(run))
    events.Reload()
    # Each checkpoint judges the siblings of nodes held out of training (and of nodes trained on).
    assert {"losses/value", "losses/siblings", "search/solved", "buffer/size", "heldout/siblings",
            "heldout/share", "heldout/search_order",
            "trained/siblings"} <= set(events.Tags()["scalars"])  # fmt: skip
    assert any(tag.startswith("edge/cube") for tag in events.Tags()["scalars"]), events.Tags()
    assert read_guide_metadata(run / "checkpoints" / str(steps[-1]))["counters"]["edge"] == edge
    assert "siblings ordered rightly on held-out nodes" in err
    guide = load_guide(run)
    task = make_task("cube4", 7)
    assert verify_labels(solve(task, time_limit=60, guide=guide)[0], task.removal).valid
    # Where the run goes on is this command's: two actors, not the one it began with. It learns from the
    # restored buffer at once and ends on its new step limit, well within the minutes.
    limit = steps[-1] + 5
    code, out, err = run_cli(
        "train-guide", "--resume", str(run), "--minutes", "1.5", "--actors", "2",
        "--max-learner-steps", str(limit), timeout=240,
    )  # fmt: skip
    assert code == 0, err
    assert f"resuming {run} at learner step {steps[-1]}" in err and "replay buffer restored" in err
    assert out.startswith(f"train-guide: {limit} learner steps"), out
    again = sorted(int(p.name) for p in (run / "checkpoints").iterdir() if p.name.isdigit())
    assert again[-1] == limit
    resumed = read_guide_metadata(run / "checkpoints" / str(limit))["config"]
    assert resumed["actors"] == 2 and resumed["search_seconds"] == 2 and resumed["max_learner_steps"] == limit
    assert set(re.findall(r"search \d+ \((\S+) K=", err)) <= {"cube4:7", "cube5:12"}
    # Each cell goes on at the K the run stopped at: a cell's first search here began before any of its
    # searches ended.
    first = dict(reversed(re.findall(r"search \d+ \((\S+) K=(\d+)", err)))
    assert all(int(pieces) == edge[cell] for cell, pieces in first.items()), (first, edge)
