"""Shared test helpers: random states and chunks for the equivalence tests, the one tiny training
config, and running the `rllock` command."""

from __future__ import annotations

import atexit
import dataclasses
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from rllock.config import LearnerConfig, MCTSConfig, NetConfig, SelfPlayConfig, TrainConfig
from rllock.core import compiled_checkers as checkers
from rllock.core import reference_checkers as ref
from rllock.core.env import State, Task, apply_chunk, candidates, initial_state, make_task


def voxel_labels(task: Task, state: State) -> dict[ref.Voxel, int]:
    return {tuple(int(c) for c in task.topology.coords[v]): int(state.labels[v]) for v in range(task.size)}


def parts_after(task: Task, state: State, chunk: np.ndarray) -> tuple[list[ref.Part], ref.Part]:
    """(P1..Pi, R_i) as coordinate sets once `chunk` becomes piece i."""
    coords = [tuple(int(c) for c in xyz) for xyz in task.topology.coords]
    labels = state.labels.copy()
    labels[chunk] = state.placed + 1
    parts = [frozenset(coords[v] for v in np.flatnonzero(labels == j)) for j in range(1, state.placed + 2)]
    return parts, frozenset(coords[v] for v in np.flatnonzero(labels == 0))


def untrained_episodes(space, mcts, batch: int, seed: int) -> tuple[Task, list]:
    """Episodes of box:4x4x2 K=3 played by the batched search with a small untrained network."""
    import jax

    from rllock.search.mcts import Searcher
    from rllock.search.network import NetConfig, PolicyValueNet, init_params

    task = make_task("box:4x4x2", 3)
    config = NetConfig(canvas=4, features=(4, 8))
    searcher = Searcher(PolicyValueNet(config), mcts, space, task, batch=batch)
    params = init_params(config, jax.random.PRNGKey(0))
    return task, searcher.play(params, task, jax.random.PRNGKey(1), seed=seed)


def save_run(run, shape: str, pieces: int, *, net, mcts, method: str = "rl-lock", step: int = 7,
             seconds: float = 600.0, validation: dict | None = None, init: str | None = None):  # fmt: skip
    """A training run folder with one best checkpoint of a fresh learner, as `rllock train` writes it
    (params, optimizer state, provenance); returns the learner."""
    import jax

    from rllock.files import checkpoint as ckpt
    from rllock.files import orbax_io
    from rllock.files.provenance import provenance
    from rllock.learner.learner import Learner, LearnerConfig
    from rllock.search.workload import SingleTask

    task = make_task(shape, pieces)
    learner = Learner(SingleTask.of(task, net.canvas), net, LearnerConfig(), jax.random.PRNGKey(3), method)
    config = TrainConfig(shape=shape, pieces=pieces, method=method, net=net, mcts=mcts, init=init)
    mngr = orbax_io.manager(run / "best", keep=1)
    counters = {"seconds": seconds, "episodes": 40}
    meta = ckpt.Metadata.of(config, task, step, validation, counters, [provenance()])
    orbax_io.save(mngr, step, learner.state(), meta.to_json())
    mngr.close()
    return learner


def save_multitask_run(run, spec: str, *, net, mcts, step: int = 5):
    """A multi-task training run folder (`rllock train --tasks spec`) with one best checkpoint of a fresh
    learner; returns the learner."""
    import jax

    from rllock.core.tasks import parse_tasks
    from rllock.files import checkpoint as ckpt
    from rllock.files import orbax_io
    from rllock.files.provenance import provenance
    from rllock.learner.learner import Learner, LearnerConfig
    from rllock.search.workload import ManyTasks

    tasks = parse_tasks(spec, canvas=net.canvas)
    net = dataclasses.replace(net, canvas=tasks.canvas, task_planes=True)
    learner = Learner(ManyTasks(tasks), net, LearnerConfig(), jax.random.PRNGKey(3))
    config = TrainConfig(tasks=spec, net=net, mcts=mcts)
    mngr = orbax_io.manager(run / "best", keep=1)
    meta = ckpt.Metadata.of(config, tasks.identity(), step, None, {}, [provenance()])
    orbax_io.save(mngr, step, learner.state(), meta.to_json())
    mngr.close()
    return learner


def reference_bits(parts: list[ref.Part], rest: ref.Part, removal: str) -> int:
    """The checks (checkers.CONNECTED | REMOVABLE | INTERLOCKING) that the reference checkers pass on the
    newest part parts[-1] and the remaining volume `rest`."""
    bits = checkers.CONNECTED if ref.is_connected(rest) else 0
    bits |= checkers.REMOVABLE if ref.is_removable(parts[-1], rest, removal) else 0
    bits |= checkers.INTERLOCKING if len(parts) < 2 or ref.is_interlocking([*parts, rest]) else 0
    return bits


def raw_chunks(task: Task, state: State, rng: np.random.Generator, count: int) -> np.ndarray:
    """Unchecked chunks from the reference sampler, as voxel numbers: int32[k, n]."""
    labels = voxel_labels(task, state)
    out = []
    for _ in range(count):
        chunk = ref.sample_chunk(labels, state.placed + 1, task.piece_size, rng)
        if chunk is not None:
            out.append([int(task.topology.index[v]) for v in chunk])
    return np.array(out, dtype=np.int32).reshape(-1, task.piece_size)


def random_valid_states(task: Task, rng: np.random.Generator, episodes: int):
    """Every state along `episodes` random walks through accepted chunks (until a dead end)."""
    for _ in range(episodes):
        state = initial_state(task)
        while state.placed < task.pieces - 1:
            yield state
            cands = candidates(
                task, state, seed=int(rng.integers(1 << 30)), num_samples=512, max_candidates=8
            )
            if len(cands) == 0:
                break
            state = apply_chunk(state, cands[rng.integers(len(cands))])


# The tiny training task every Ray test uses: seconds per learner step, not minutes.
TINY = TrainConfig(
    shape="box:4x4x2",
    pieces=3,
    net=NetConfig(features=(4, 8)),
    mcts=MCTSConfig(simulations=8, max_considered=4, raw_samples=256, candidates=8),
    learner=LearnerConfig(learning_rate=1e-3, batch_size=16),
    selfplay=SelfPlayConfig(actors=1, episodes_per_batch=4),
    min_buffer=8,
    publish_every=5,
    max_policy_lag=2,
    validate_minutes=0.3,
    validation_episodes=8,
    checkpoint_minutes=0.05,
)


def tiny_flags(config: TrainConfig = TINY, **changes) -> list[str]:
    """`rllock train` flags that give `config` (top-level fields replaced by `changes`), leaving out
    --logdir and --minutes, which each test sets."""
    from rllock.orchestration.cli.flags import leaves

    config = dataclasses.replace(config, **changes)
    flags = []
    for path, _, _ in leaves(TrainConfig):
        if path[-1] in ("logdir", "minutes"):
            continue
        value = config
        for name in path:
            value = getattr(value, name)
        flag = "--" + path[-1].replace("_", "-")
        if value is None:
            continue
        if isinstance(value, bool):
            flags.append(flag if value else "--no-" + flag[2:])
        else:
            flags += [flag, ",".join(map(str, value)) if isinstance(value, tuple) else str(value)]
    return flags


# Commands with these flags start processes that import the command's own main module (multiprocessing's
# spawn) or measure what their processes cost: they run in a fresh interpreter, as a user runs them.
FRESH_FLAGS = frozenset({"--workers", "--threads", "--address"})


class _CliServer:
    """`tests/cli_server.py`: forks the `rllock` command with its imports already paid, one request at a
    time (a pytest worker runs one test at a time). Made for the environment it was started in."""

    def __init__(self) -> None:
        self.env = _environment()
        self.proc = subprocess.Popen(
            [sys.executable, str(Path(__file__).with_name("cli_server.py"))],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.requests, self.replies = self.proc.stdin, self.proc.stdout
        if self.replies.readline() != "ready\n":
            raise RuntimeError("tests/cli_server.py did not start")
        atexit.register(self.close)

    def run(self, args: list[str], timeout: float) -> tuple[int, str, str]:
        with tempfile.TemporaryDirectory(prefix="rllock-cli-") as folder:
            out, err = Path(folder, "stdout"), Path(folder, "stderr")
            request = {"args": args, "cwd": os.getcwd(), "out": str(out), "err": str(err), "timeout": timeout}
            self.requests.write(json.dumps(request) + "\n")
            self.requests.flush()
            line = self.replies.readline()
            if not line:
                raise RuntimeError("tests/cli_server.py died")
            reply = json.loads(line)
            if reply.get("timeout"):
                raise subprocess.TimeoutExpired(["rllock", *args], timeout)
            return reply["code"], out.read_text(), err.read_text()

    def close(self) -> None:
        self.requests.close()
        self.proc.wait(timeout=30)


_server: list[_CliServer] = []


def _environment() -> dict[str, str]:
    """The environment a command would get, less what pytest changes from test to test."""
    return {k: v for k, v in os.environ.items() if k != "PYTEST_CURRENT_TEST"}


def run_cli(*args: str, timeout: float = 300) -> tuple[int, str, str]:
    """Run the `rllock` command (`python -m rllock.orchestration.cli ARGS`) as a process of its own: (exit
    code, stdout, stderr). Forked from `tests/cli_server.py`, which has imported it already, unless the
    command starts processes (`FRESH_FLAGS`); a server is started again for a changed environment."""
    if not FRESH_FLAGS.isdisjoint(args):
        return _fresh_cli(args, timeout)
    if _server and (_server[0].proc.poll() is not None or _server[0].env != _environment()):
        _server.pop().close()
    if not _server:
        _server.append(_CliServer())
    return _server[0].run(list(args), timeout)


def _fresh_cli(args: tuple[str, ...], timeout: float) -> tuple[int, str, str]:
    proc = subprocess.run(
        [sys.executable, "-m", "rllock.orchestration.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    return proc.returncode, proc.stdout, proc.stderr


def reference_verdict(labels: np.ndarray, removal: str) -> tuple[bool, int | None, str | None, list]:
    """(valid, failed stage, failed check, disassembly) by the reference checkers applied to every stage
    as docs/checkers.md says, plainly: what `rllock.core.verifier` must agree with."""
    from dataclasses import asdict

    from rllock.core.verifier import Move, _runs

    k = int(labels.max())
    cells = {j: frozenset(ref.voxel(v) for v in np.argwhere(labels == j)) for j in range(1, k + 1)}
    disassembly = []
    for i in range(1, k):
        parts = [cells[j] for j in range(1, i + 1)]
        rest = frozenset().union(*(cells[j] for j in range(i + 1, k + 1)))
        if not all(ref.is_connected(p) for p in parts) or not ref.is_connected(rest):
            return False, i, "connected", []
        if removal == "straight":
            exit_ = ref.straight_exit(parts[-1], rest)
            moves = None if exit_ is None else [Move(ref.DIRECTION_NAMES[exit_[0]], exit_[1])]
        else:
            path = ref.path_exit(parts[-1], rest)
            moves = None if path is None else _runs(path)
        if moves is None:
            return False, i, "removable", []
        if len(parts) >= 2 and not ref.is_interlocking([*parts, rest]):
            return False, i, "interlocking", []
        disassembly.append({"piece": i, "moves": [asdict(m) for m in moves]})
    return True, None, None, disassembly


def actor_nodes(api: str, class_name: str = "SelfPlayActor") -> set[str]:
    """The nodes where actors of `class_name` are alive, from Ray's state API."""
    from ray.util.state import list_actors

    alive = list_actors(address=api, filters=[("class_name", "=", class_name), ("state", "=", "ALIVE")])
    return {a.node_id for a in alive}
