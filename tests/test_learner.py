from __future__ import annotations

import shutil
import threading

import jax
import numpy as np
import pytest
from helpers import TINY, untrained_episodes

from rllock.config import TrainConfig
from rllock.core.env import make_task
from rllock.errors import RLLockError
from rllock.files import checkpoint as ckpt
from rllock.files import orbax_io
from rllock.learner.learner import Learner, LearnerConfig
from rllock.learner.replay import ReplayBuffer
from rllock.orchestration.recorder import validation_rank
from rllock.search.inference import load_policy
from rllock.search.mcts import ChunkStore, MCTSConfig
from rllock.search.network import NetConfig
from rllock.search.workload import SingleTask

NET = NetConfig(canvas=4, features=(4, 8))
MCTS = MCTSConfig(simulations=8, max_considered=4, raw_samples=256, candidates=8)
assert TINY.net.features == NET.features and TINY.mcts == MCTS  # the same programs as the Ray tests


@pytest.fixture(scope="module")
def task_and_episodes():
    # The Ray tests' task, network and learner (helpers.TINY): one compiled update step for all of them.
    return untrained_episodes(ChunkStore, MCTS, batch=6, seed=3)


def test_replay_buffer_is_a_bounded_ring(task_and_episodes):
    task, eps = task_and_episodes
    total = sum(len(e.z) for e in eps)
    buf = ReplayBuffer(capacity=total - 3, n_voxels=task.size, candidates=8, piece_size=task.piece_size)
    buf.add_many(eps)
    assert len(buf) == total - 3 and buf.added == total
    flat = np.concatenate([e.labels for e in eps])  # every transition, oldest first
    # Transitions 0..2 were overwritten by the last three, which wrapped around to slots 0..2.
    assert buf.cursor == 3
    np.testing.assert_array_equal(buf.labels[:3], flat[-3:])
    np.testing.assert_array_equal(buf.labels[3:], flat[3:-3])
    sample = buf.sample(5, seed=0)
    assert sample["labels"].shape == (5, task.size) and sample["chunks"].dtype == np.int16


def test_learners_of_one_network_and_learning_rate_share_one_compiled_step(task_and_episodes):
    from rllock.learner.learner import update_step

    task, eps = task_and_episodes
    buf = ReplayBuffer(1000, task.size, 8, task.piece_size)
    buf.add_many(eps)
    sample = buf.sample(16, seed=0)
    config = TINY.learner
    first = Learner(SingleTask.of(task, 4), NET, config, jax.random.PRNGKey(0))
    first.update(sample)
    compiled = update_step._cache_size()
    second = Learner(SingleTask.of(task, 4), NET, config, jax.random.PRNGKey(1))
    second.update(sample)
    assert second.optimizer is first.optimizer and update_step._cache_size() == compiled
    Learner(SingleTask.of(task, 4), NET, LearnerConfig(learning_rate=2e-3), jax.random.PRNGKey(0)).update(
        sample
    )
    assert update_step._cache_size() == compiled + 1  # another learning rate: another step


def test_learner_fits_a_fixed_batch(task_and_episodes):
    task, eps = task_and_episodes
    buf = ReplayBuffer(1000, task.size, 8, task.piece_size)
    buf.add_many(eps)
    batch = buf.sample(32, seed=0)
    # Without symmetries, so that every update sees exactly this batch.
    learner = Learner(
        SingleTask.of(task, 4),
        NET,
        LearnerConfig(learning_rate=3e-3, batch_size=32, symmetries=False),
        jax.random.PRNGKey(0),
    )
    first = learner.update(batch)
    for _ in range(60):
        last = learner.update(batch)
    assert learner.step == 61
    assert (
        np.isfinite(first["policy"]) and last["value"] < first["value"] and last["policy"] < first["policy"]
    )


def _save(tmp_path, task, learner):
    config = TrainConfig(shape="box:4x4x2", pieces=3, net=NET, mcts=MCTS)
    mngr = orbax_io.manager(tmp_path / "run" / "best", keep=1)
    orbax_io.save(mngr, learner.step, learner.state(), ckpt.Metadata.of(config, task, learner.step).to_json())
    mngr.close()
    return tmp_path / "run"


def test_checkpoint_round_trip_restores_params_and_task(tmp_path, task_and_episodes):
    task, eps = task_and_episodes
    learner = Learner(SingleTask.of(task, 4), NET, TINY.learner, jax.random.PRNGKey(5))
    buf = ReplayBuffer(1000, task.size, 8, task.piece_size)
    buf.add_many(eps)
    learner.update(buf.sample(16, seed=1))
    run = _save(tmp_path, task, learner)
    policy = load_policy(run)
    assert policy.step == 1 and policy.task.pieces == 3 and policy.net == NET and policy.mcts == MCTS
    assert np.array_equal(policy.task.topology.grid, task.topology.grid)
    for a, b in zip(jax.tree_util.tree_leaves(policy.params), jax.tree_util.tree_leaves(learner.params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_saving_a_step_again_replaces_it_and_never_leaves_the_folder_without_it(tmp_path, task_and_episodes):
    """A periodic checkpoint while the learner waits (no new step) saves the same step again."""
    task, _ = task_and_episodes
    learner = Learner(SingleTask.of(task, 4), NET, LearnerConfig(), jax.random.PRNGKey(5))
    config = TrainConfig(shape="box:4x4x2", pieces=3, net=NET, mcts=MCTS)
    folder = tmp_path / "run" / "checkpoints"
    mngr = orbax_io.manager(folder, keep=3)
    orbax_io.save(mngr, 0, learner.state(), ckpt.Metadata.of(config, task, 0).to_json())
    seen: list[list[int]] = []
    stop = threading.Event()

    def poll() -> None:
        while not stop.is_set():
            seen.append(ckpt.saved_steps(folder))

    poller = threading.Thread(target=poll)
    poller.start()
    try:
        for counters in ({"episodes": 1}, {"episodes": 2}):
            meta = ckpt.Metadata.of(config, task, 0, counters=counters).to_json()
            orbax_io.save(mngr, 0, learner.state(), meta)
    finally:
        stop.set()
        poller.join()
    assert len(seen) > 10 and all(steps == [0] for steps in seen), {tuple(s) for s in seen}
    assert mngr.all_steps() == [0] and sorted(p.name for p in folder.parent.iterdir()) == ["checkpoints"]
    assert ckpt.read_metadata(folder / "0").counters == {"episodes": 2}
    mngr.close()


@pytest.mark.parametrize("atomic", [True, False])
def test_exchange_swaps_two_folders_with_or_without_renameat2(tmp_path, monkeypatch, atomic):
    if not atomic:
        monkeypatch.setattr(orbax_io.ctypes, "CDLL", lambda *args, **kwargs: object())
    a, b = tmp_path / "staging" / "3", tmp_path / "checkpoints" / "3"
    for folder, text in ((a, "new"), (b, "old")):
        folder.mkdir(parents=True)
        (folder / "f").write_text(text)
    orbax_io._exchange(a, b)
    assert (b / "f").read_text() == "new" and (a / "f").read_text() == "old"
    assert sorted(p.name for p in b.parent.iterdir()) == ["3"]


def test_checkpoint_for_another_task_or_corrupted_is_an_error(tmp_path, task_and_episodes):
    task, _ = task_and_episodes
    run = _save(tmp_path, task, Learner(SingleTask.of(task, 4), NET, LearnerConfig(), jax.random.PRNGKey(5)))
    other = make_task("box:4x4x2", 4)
    with pytest.raises(RLLockError, match=r"another task: box:4x4x2 \(4x4x2\) K=3, .*; this task is .*K=4"):
        load_policy(run, other)
    step_dir = ckpt.find_step_dir(run)
    broken = tmp_path / "broken"
    shutil.copytree(step_dir, broken)
    for f in (broken / "state").rglob("*"):
        if f.is_file() and f.stat().st_size > 0 and "ocdbt" not in f.name and f.parent.name == "d":
            f.write_bytes(b"\0" * 7)
    with pytest.raises(RLLockError, match="corrupted"):
        load_policy(broken)
    (broken / "meta" / "metadata").write_text("{trunc")
    with pytest.raises(RLLockError, match="corrupted"):
        load_policy(broken)


def test_validations_rank_by_success_then_by_how_far_episodes_got():
    none_valid_far = {"success_rate": 0.0, "mean_return": 0.7}
    none_valid_near = {"success_rate": 0.0, "mean_return": 0.6}
    one_valid = {"success_rate": 1 / 64, "mean_return": 0.5}
    assert validation_rank(none_valid_far) > validation_rank(none_valid_near)
    assert validation_rank(one_valid) > validation_rank(none_valid_far)
    assert validation_rank(None) < validation_rank(none_valid_near)
    assert validation_rank({"success_rate": 0.0}) < validation_rank(none_valid_near)  # older checkpoints
