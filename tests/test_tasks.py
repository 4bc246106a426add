"""Multi-task training's pieces: task specs, random shapes, canvas states and their symmetries."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    parts_after,
    random_valid_states,
    raw_chunks,
    reference_bits,
    run_cli,
    save_multitask_run,
    save_run,
)
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from rllock.actors.selfplay import PlaySpec, SelfPlayWorker
from rllock.config import LearnerConfig, MCTSConfig, NetConfig, TrainConfig
from rllock.core.env import State, make_task
from rllock.core.shapes import crop, is_connected
from rllock.core.tasks import parse_tasks, random_shape
from rllock.core.verifier import verify_labels
from rllock.errors import RLLockError
from rllock.files.assembly import read_assembly
from rllock.files.checkpoint import find_step_dir, read_metadata
from rllock.learner.learner import Learner
from rllock.learner.replay import ReplayBuffer
from rllock.orchestration.bench.arms import Arm
from rllock.orchestration.bench.transfer import (
    TransferTask,
    bench_transfer_task,
    format_transfer_table,
    parse_transfer_tasks,
    ratio,
    trained_on,
)
from rllock.orchestration.builder import workload_of
from rllock.orchestration.cli.main import main
from rllock.orchestration.recorder import Counters, Recorder
from rllock.orchestration.validation import Plan, Validator
from rllock.search import pretrained
from rllock.search.canvas import augment_canvas, canvas_episode, crop_canvas
from rllock.search.inference import load_network, load_policy, with_simulations
from rllock.search.network import (
    TASK_SCALE,
    canvas_index,
    chunk_logits,
    encode_batch,
    encode_canvas,
    init_params,
    to_canvas,
)
from rllock.search.workload import ManyTasks, SingleTask

SPEC = "cube4:6-9,box:6x5x4:8-12,random:60-200:6-20"


def test_spec_parses_into_groups_on_the_papers_canvas():
    tasks = parse_tasks(SPEC)
    assert tasks.canvas == 8 and [g.pieces for g in tasks.groups] == [(6, 9), (8, 12), (6, 20)]
    assert tasks.groups[1].grid.shape == (6, 5, 4) and tasks.groups[2].sizes == (60, 200)
    assert tasks.max_piece_size() == 200 // 6
    assert parse_tasks("cube9:10").canvas == 12  # grows to fit a larger shape, in steps of 4


@pytest.mark.parametrize(
    "spec,message",
    [
        ("", "empty"),
        ("cube4", "no piece count"),
        ("cube4:9-6", "9-6"),
        ("cube4:x", "bad piece count"),
        ("cube4:1-3", "at least 2"),
        ("cube2:9", "exceeds the shape"),
        ("nosuchshape:4", "unknown shape"),
        ("cube9:10", "does not fit"),
        ("random:600:4", "exceed the 8\\^3 canvas"),
        ("random:600-900:4@8", "exceed the 8\\^3 canvas"),
        ("cube9:10@8", "does not fit the 8\\^3"),
        ("cube4:6@10", "bad canvas '10'"),
        ("cube4:6@x", "bad canvas 'x'"),
    ],
)
def test_bad_specs_are_one_line_errors(spec, message):
    with pytest.raises(RLLockError, match=message):
        parse_tasks(spec, canvas=8 if "cube9" in spec or "random" in spec else None)


def test_groups_play_on_their_own_canvas_and_the_run_stores_on_the_largest():
    tasks = parse_tasks("cube4:6-9,random:200-500:10-40@12,cube9:10@16")
    assert [g.canvas for g in tasks.groups] == [8, 12, 16]
    assert (tasks.canvas, tasks.store_canvas, tasks.canvases()) == (8, 16, (8, 12, 16))
    assert tasks.identity()["canvases"] == [8, 12, 16] and tasks.identity()["canvas"] == 8
    assert [t.shape_name for t in tasks.validation_tasks(0)][2] == "cube9"
    rng = np.random.default_rng(3)
    for _ in range(12):
        g, task = tasks.draw(rng)
        assert max(task.topology.dims) <= tasks.groups[g].canvas
    # A random group on a larger canvas grows shapes the run's canvas could not hold.
    big = parse_tasks("random:700-800:20@12", canvas=8)
    assert big.canvas == 12 and big.draw(rng)[1].size >= 700


def test_random_shapes_are_connected_compact_solids_of_the_asked_size():
    rng = np.random.default_rng(0)
    for size in (4, 60, 137, 200):
        grid = random_shape(rng, size, 8)
        assert grid.sum() == size and max(grid.shape) <= 8 and is_connected(grid)
        assert np.array_equal(grid, crop(grid))
        if size >= 60:  # compact: fills at least a third of its bounding box (a tree would not)
            assert grid.sum() / grid.size > 1 / 3
    a, b = random_shape(np.random.default_rng(5), 90, 8), random_shape(np.random.default_rng(5), 90, 8)
    assert np.array_equal(a, b)


def test_draws_cover_every_group_within_its_ranges():
    tasks = parse_tasks(SPEC)
    rng = np.random.default_rng(1)
    seen = set()
    for _ in range(60):
        g, task = tasks.draw(rng)
        seen.add(g)
        lo, hi = tasks.groups[g].pieces
        assert lo <= task.pieces <= hi and max(task.topology.dims) <= tasks.canvas
        assert task.piece_size <= tasks.max_piece_size()
        if tasks.groups[g].sizes is not None:
            assert 60 <= task.size <= 200 and task.piece_size >= 2
    assert seen == {0, 1, 2}
    small = parse_tasks("random:4-11:6-8")  # K is cut to N/2 here
    for _ in range(20):
        _, task = small.draw(rng)
        assert 2 <= task.pieces <= task.size // 2 and task.piece_size <= small.max_piece_size()
    first = [(t.shape_name, t.pieces) for t in tasks.validation_tasks(7)]
    assert first == [(t.shape_name, t.pieces) for t in tasks.validation_tasks(7)]  # fixed
    assert first[0] == ("cube4", 7)


def reference_planes(task, labels: np.ndarray, placed: int, canvas: int, task_planes: bool) -> np.ndarray:
    """The module docstring's planes, voxel by voxel."""
    k, n = task.pieces, task.piece_size
    out = np.zeros((canvas, canvas, canvas, 9 if task_planes else 7), np.float32)
    for v, (x, y, z) in enumerate(task.topology.coords):
        j = int(labels[v])
        row = [1, j == 0, j > 0, j / k, j == 1, j == placed and placed > 0, placed / k]
        if task_planes:
            row += [n / TASK_SCALE, k / TASK_SCALE]
        out[x, y, z] = row
    return out


@pytest.mark.parametrize("task_planes", [False, True])
def test_encoding_matches_a_voxel_by_voxel_reference(task_planes):
    task = make_task("box:5x3x2", 5)  # N = 30, n = 6
    rng = np.random.default_rng(0)
    for state in list(random_valid_states(task, rng, 3))[:6]:
        got = encode_batch(task, state.labels[None], np.array([state.placed]), 8, task_planes)[0]
        want = reference_planes(task, state.labels, state.placed, 8, task_planes)
        np.testing.assert_allclose(got, want, rtol=1e-6)
        from_canvas = encode_canvas(
            to_canvas(task, state.labels[None], 8), np.array([state.placed]), np.array([5]), 8, task_planes
        )[0]
        np.testing.assert_allclose(from_canvas, want, rtol=1e-6)


def test_padded_chunks_score_like_unpadded_ones():
    logits = jax.random.normal(jax.random.PRNGKey(0), (2, 64))
    chunks = jnp.array(np.random.default_rng(0).integers(0, 64, (2, 5, 3)))
    valid = jnp.ones((2, 5), bool)
    padded = jnp.concatenate([chunks, -jnp.ones((2, 5, 4), chunks.dtype)], axis=-1)
    np.testing.assert_allclose(
        chunk_logits(logits, padded, valid), chunk_logits(logits, chunks, valid), rtol=1e-6
    )


def l_shape() -> np.ndarray:
    """An L-shaped block without symmetries that map it onto itself, other than the identity."""
    grid = np.zeros((4, 3, 2), bool)
    grid[:, 0, :] = True
    grid[0, :, :] = True
    grid[3, 1, 0] = True
    return grid


def test_box_symmetries_map_states_to_states_of_the_moved_shape_with_the_same_checks():
    """Every augmented transition is a state of the rotated or mirrored shape, and each candidate chunk
    passes exactly the reference checks there that it passed on the original."""
    task = make_task(l_shape(), 4)  # N = 13, n = 3
    canvas, piece, n = 8, 6, 3
    rng = np.random.default_rng(3)
    maps_used = set()
    compared = 0
    for i, state in enumerate(list(random_valid_states(task, rng, 8))[:12]):
        chunks = raw_chunks(task, state, rng, 6)
        if len(chunks) == 0:
            continue
        sample = {
            "labels": to_canvas(task, state.labels[None], canvas),
            "chunks": np.pad(
                canvas_index(task, canvas)[chunks], ((0, 0), (0, piece - n)), constant_values=-1
            )[None].astype(np.int16),
        }
        for seed in range(4):
            moved = augment_canvas(sample, canvas, 10 * i + seed)
            cells = moved["labels"][0].reshape(canvas, canvas, canvas)
            grid = cells >= 0
            assert grid[0].any() and grid[:, 0].any() and grid[:, :, 0].any()  # still at the origin
            assert grid.sum() == task.size
            maps_used.add(grid.tobytes())
            image = make_task(crop(grid), 4)
            idx = canvas_index(image, canvas)
            image_state = State(moved["labels"][0][idx].astype(np.int16), state.placed)
            voxel_of = {int(c): v for v, c in enumerate(idx)}
            for chunk, moved_chunk in zip(chunks, moved["chunks"][0]):
                assert (moved_chunk[n:] == -1).all()
                image_chunk = np.array([voxel_of[int(c)] for c in moved_chunk[:n]])
                before = reference_bits(*parts_after(task, state, chunk), "straight")
                after = reference_bits(*parts_after(image, image_state, image_chunk), "straight")
                assert before == after
                compared += 1
    assert compared >= 30 and len(maps_used) > 4  # several distinct images of the shape


def test_a_run_on_two_canvases_learns_each_batch_on_the_canvas_it_was_played_on():
    """A worker on a task set plays a drawn task (groups on a 4^3 and an 8^3 canvas); its episodes come
    as canvas states, stored on 8^3. Every batch comes from one canvas, cropped to it, and the learner's
    planes equal the single-task encoding of the same states on that canvas; both kinds of batch update
    the network (one network, two compiled shapes)."""
    tasks = parse_tasks("box:4x3x2:3-4,cube3:3@8", canvas=4)
    assert [g.canvas for g in tasks.groups] == [4, 8] and tasks.store_canvas == 8
    net = NetConfig(canvas=4, features=(4, 8), task_planes=True)
    mcts = MCTSConfig(simulations=4, max_considered=4, raw_samples=64, candidates=4)
    worker = SelfPlayWorker(PlaySpec(ManyTasks(tasks), net, mcts, "rl-lock", episodes=4), seed=0)
    worker.set_weights(init_params(net, jax.random.PRNGKey(0)), 0)
    buffer = ReplayBuffer(400, 512, 4, tasks.max_piece_size(), store_canvas=8)
    played, groups = set(), set()
    for _ in range(4):
        episodes, stats = worker.play()
        played.add(stats.canvas)
        groups.add(stats.group)
        assert all(e.labels.shape[1] == 512 for e in episodes)
        buffer.add_many(episodes, stats.pieces, stats.canvas)
    assert played == {4, 8} and groups == {0, 1} and {c for _, c in worker.compiled} == {4, 8}
    learner = Learner(ManyTasks(tasks), net, LearnerConfig(batch_size=8), jax.random.PRNGKey(1))
    seen = set()
    for seed in range(8):
        sample = buffer.sample(8, seed=seed, success_fraction=0.5)
        side = int(sample["canvas"])
        seen.add(side)
        assert sample["labels"].shape == (8, side**3)
        planes, chunks, valid, _, _ = learner.prepare(sample)
        assert planes.shape[1:4] == (side,) * 3
        for row in range(8):
            on = sample["labels"][row] >= 0
            task = make_task(crop(on.reshape((side,) * 3)), int(sample["pieces"][row]))
            assert task.piece_size == int(on.sum()) // task.pieces
            assert task.shape_name and (side == 4) == (task.topology.dims == (4, 3, 2))
            labels = sample["labels"][row][canvas_index(task, side)]
            want = encode_batch(task, labels[None], sample["placed"][row : row + 1], side, True)[0]
            np.testing.assert_allclose(planes[row], want)
            real = chunks[row][valid[row]]
            assert (real < side**3).all() and ((real >= 0).sum(axis=1) == task.piece_size).all()
            assert on[real[real >= 0]].all()  # candidates lie on the shape, on the cropped canvas
        before = learner.params
        learner.update(sample)
        assert learner.step == seed + 1 and not all(
            np.array_equal(a, b) for a, b in zip(jax.tree.leaves(before), jax.tree.leaves(learner.params))
        )
    assert seen == {4, 8}


def test_crop_canvas_gives_the_states_as_played_on_the_smaller_canvas():
    task = make_task("box:4x3x2", 3)
    rng = np.random.default_rng(0)
    labels = rng.integers(0, 4, size=(5, task.size)).astype(np.int8)
    chunks = rng.integers(0, task.size, size=(5, 3, 6))
    pad = np.full((5, 3, 2), -1)

    def stored(canvas):
        idx = canvas_index(task, canvas)
        return {
            "labels": to_canvas(task, labels, canvas),
            "chunks": np.concatenate([idx[chunks], pad], axis=2).astype(np.int16),
        }

    cropped = crop_canvas(stored(12), 12, 4)
    for key in ("labels", "chunks"):
        np.testing.assert_array_equal(cropped[key], stored(4)[key])
    with pytest.raises(ValueError, match="does not fit"):
        crop_canvas(stored(12), 12, 2)


def test_canvas_episode_pads_chunks_and_marks_the_shape():
    tasks = parse_tasks("box:4x3x2:4", canvas=4)
    net = NetConfig(canvas=4, features=(4, 8), task_planes=True)
    mcts = MCTSConfig(simulations=4, max_considered=4, raw_samples=64, candidates=4)
    worker = SelfPlayWorker(PlaySpec(ManyTasks(tasks), net, mcts, "rl-lock", episodes=2), seed=1)
    task = tasks.validation_tasks(0)[0]
    episode = worker.searchers(task, 4)[0].play(
        init_params(net, jax.random.PRNGKey(0)), task, jax.random.PRNGKey(0), seed=0
    )[0]
    out = canvas_episode(task, episode, 4, 9)
    assert out.labels.shape == (len(episode.z), 64) and (out.labels >= 0).sum(axis=1).tolist() == [24] * len(
        episode.z
    )
    assert (out.chunks[:, :, 6:] == -1).all()
    for t in range(len(episode.z)):
        m = int(episode.num_valid[t])
        np.testing.assert_array_equal(out.chunks[t, :m, :6], canvas_index(task, 4)[episode.chunks[t, :m]])
        assert (out.chunks[t, m:] == -1).all()


MULTI_NET = NetConfig(canvas=4, features=(4, 8))
MULTI_MCTS = MCTSConfig(simulations=4, max_considered=4, raw_samples=128, candidates=8)


def test_a_multitask_checkpoint_generates_verified_assemblies_for_a_task_it_never_saw(tmp_path, capsys):
    save_multitask_run(tmp_path / "run", "cube3:3-4,random:12-30:3-5", net=MULTI_NET, mcts=MULTI_MCTS)
    out = tmp_path / "out"
    code, stdout, err = run_cli(
        "generate", "--checkpoint", str(tmp_path / "run"), "--shape", "box:4x3x2", "--pieces", "3",
        "--count", "2", "--batch", "16", "--time-limit", "60", "--simulations", "6", "--out", str(out),
    )  # fmt: skip
    assert code == 0, err
    written = sorted(out.glob("assembly_*"))
    assert len(written) == 2 and "box:4x3x2 K=3" in stdout
    for folder in written:
        labels, meta = read_assembly(folder)
        assert verify_labels(labels).valid and labels.shape == (4, 3, 2) and labels.max() == 3
        assert meta["method"]["simulations"] == 6 != MULTI_MCTS.simulations
    assert main(["generate", "--checkpoint", str(tmp_path / "run"), "--out", str(tmp_path / "o2")]) == 2
    assert "serves many tasks" in capsys.readouterr().err.strip().splitlines()[-1]
    run = ["generate", "--checkpoint", str(tmp_path / "run"), "--shape", "cube3", "--pieces", "3"]
    assert main([*run, "--simulations", "0", "--out", str(tmp_path / "o3")]) == 2
    assert capsys.readouterr().err.strip() == "rllock: error: --simulations must be at least 1, got 0"
    policy = load_policy(tmp_path / "run", make_task("cube3", 3))
    with pytest.raises(RLLockError, match="runs no search"):
        with_simulations(dataclasses.replace(policy, method="ppo"), 8)
    # beyond its 4^3 canvas it plays on the smallest that fits, up to MAX_CANVAS
    assert load_policy(tmp_path / "run", make_task("box:5x3x2", 3)).net.canvas == 6  # step 2
    with pytest.raises(RLLockError, match="does not fit the largest canvas"):
        load_policy(tmp_path / "run", make_task("box:17x3x2", 3))


def test_a_multitask_checkpoint_ships_and_lists_its_task_groups(tmp_path):
    save_multitask_run(tmp_path / "run", "cube3:3-4,random:12-30:3-5", net=MULTI_NET, mcts=MULTI_MCTS)
    pretrained.ship(tmp_path / "run", "general", into=tmp_path / "shipped")
    row = pretrained.describe("general", tmp_path / "shipped")
    assert row["task"] == "tasks cube3:3-4,random:12-30:3-5" and row["canvas"] == 4


def test_init_starts_a_run_from_another_checkpoints_network(tmp_path):
    saved = save_multitask_run(tmp_path / "run", "cube3:3-4", net=MULTI_NET, mcts=MULTI_MCTS)
    config = TrainConfig(shape="box:4x3x2", pieces=4, init=str(tmp_path / "run"))
    config, workload, init = workload_of(config)
    assert isinstance(workload, SingleTask) and workload.identity()["pieces"] == 4
    assert config.net.task_planes and config.net.canvas == 4 and config.net.features == (4, 8)
    learner = Learner(workload, config.net, LearnerConfig(), jax.random.PRNGKey(9))
    learner.start_from(load_network(init)[2])  # workload_of opens the checkpoint; its weights load later
    for a, b in zip(jax.tree.leaves(saved.params), jax.tree.leaves(learner.params)):
        np.testing.assert_array_equal(a, b)
    assert learner.step == 0


def test_init_fine_tunes_a_generalist_on_a_smaller_canvas(tmp_path):
    """--canvas with --init: the same weights on the smallest canvas that fits the task."""
    saved = save_multitask_run(
        tmp_path / "run", "cube3:3-4", net=dataclasses.replace(MULTI_NET, canvas=6), mcts=MULTI_MCTS
    )
    small = TrainConfig(shape="box:4x3x2", pieces=4, init=str(tmp_path / "run"), net=NetConfig(canvas=4))
    config, workload, init = workload_of(small)
    assert config.net.canvas == workload.identity()["canvas"] == 4
    assert config.net.features == (4, 8) and config.net.task_planes
    learner = Learner(workload, config.net, LearnerConfig(), jax.random.PRNGKey(9))
    learner.start_from(load_network(init)[2])  # workload_of opens the checkpoint; its weights load later
    for a, b in zip(jax.tree.leaves(saved.params), jax.tree.leaves(learner.params)):
        np.testing.assert_array_equal(a, b)
    assert workload_of(dataclasses.replace(small, net=NetConfig()))[0].net.canvas == 6
    with pytest.raises(RLLockError, match="does not fit"):
        workload_of(dataclasses.replace(small, net=NetConfig(canvas=2)))


def test_transfer_tasks_and_ratios():
    tasks = parse_transfer_tasks("sofa:12, cube4-k9,box:4x3x2:3")
    assert [(t.shape, t.pieces, t.name) for t in tasks] == [
        ("sofa", 12, "sofa-k12"),
        ("cube4", 9, "cube4-k9"),
        ("box:4x3x2", 3, "box:4x3x2-k3"),
    ]
    assert len(parse_transfer_tasks(None)) == 10
    with pytest.raises(RLLockError, match="SHAPE:K"):
        parse_transfer_tasks("sofa")
    assert ratio(Arm(5, 64, 10.0), Arm(5, 128, 40.0)) == "0.25"
    assert ratio(Arm(5, 64, 10.0), Arm(0, 640, 100.0)) == "<= 0.02"  # 2 s per valid, over 100 s
    assert ratio(Arm(0, 64, 10.0), Arm(5, 64, 10.0)) is None


def test_bench_transfer_runs_every_arm_and_knows_which_shapes_were_trained(tmp_path):
    save_multitask_run(tmp_path / "run", "box:4x3x2:3-4,random:12-30:3-5", net=MULTI_NET, mcts=MULTI_MCTS)
    protocol = dict(count=1, batch=8, time_limit=30, seed=0)
    row = bench_transfer_task(str(tmp_path / "run"), TransferTask("box:3x3x2", 2), simulations=2, **protocol)
    assert not row.seen and row.per_task is None
    assert row.simulations == 2 != MULTI_MCTS.simulations and row.per_task_simulations is None
    assert row.zero_shot.valid == row.untrained.valid == row.solver.valid == 1
    table = format_transfer_table([row], dict(count=1, batch=8, time_limit=30), "rllock bench transfer")
    assert "1 wanted, batches of 8, 30 s limit per arm" in table and "| box:3x3x2 K=2 | no | 2 |" in table
    meta = read_metadata(find_step_dir(tmp_path / "run"))
    assert trained_on(meta, make_task("box:4x3x2", 4)) and not trained_on(meta, make_task("box:3x4x2", 4))
    single = tmp_path / "single"
    save_run(single, "box:4x3x2", 3, net=MULTI_NET, mcts=MULTI_MCTS)
    with pytest.raises(RLLockError, match="one task"):
        bench_transfer_task(str(single), TransferTask("box:4x3x2", 3), **protocol)


def test_multitask_validation_scores_each_group_in_tensorboard_and_keeps_the_best(tmp_path):
    """One validation of a multi-task run (no Ray needed): a fixed task per group, a score per group
    and their mean, TensorBoard tags per group, and the best checkpoint saved for the task set."""
    config = TrainConfig(
        tasks="box:4x3x2:3,cube3:3",
        net=MULTI_NET,
        mcts=MULTI_MCTS,
        validation_episodes=4,
        logdir=str(tmp_path),
    )
    config, workload, _ = workload_of(config)
    learner = Learner(workload, config.net, config.learner, jax.random.PRNGKey(0))
    recorder = Recorder(tmp_path, config, workload.identity(), 0, False, [])
    score = Validator(Plan.of(config, workload), None).run(learner, recorder, Counters())
    recorder.close()
    assert score.groups is not None
    assert list(score.groups) == ["box:4x3x2:3", "cube3:3"] and score.episodes == 8
    rates = [g["success_rate"] for g in score.groups.values()]
    assert score.success_rate == pytest.approx(np.mean(rates))
    assert [g["task"] for g in score.groups.values()] == ["box:4x3x2 K=3", "cube3 K=3"]
    events = EventAccumulator(str(tmp_path))
    events.Reload()
    tags = set(events.Tags()["scalars"])
    assert {"validation/box_4x3x2_3/success_rate", "validation/cube3_3/success_rate"} <= tags
    meta = read_metadata(find_step_dir(tmp_path))
    assert meta.task["tasks"] == "box:4x3x2:3,cube3:3" and meta.validation["groups"]
