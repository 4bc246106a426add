"""`rllock train-guide --replay-from`: the guide network trained on replay snapshots already made.

Searches are what a guide run spends its time on; the learner's steps are cheap. This trains a fresh
network (or resumes one) on every state of one or more runs' replay snapshots at once
(`learner.guide_learner.pool`), with the same learner, TensorBoard events, held-out judgement and
checkpoints as `rllock train-guide`, in one process: no Ray, no actors. Each checkpoint's metadata
records the snapshots it learned from (path, states, SHA-256), so a shipped guide names its data.
`--minutes` is a hard budget; `--resume LOGDIR` goes on from the newest readable checkpoint on the same
snapshots (checked by their hashes); Ctrl-C and SIGTERM stop with a final checkpoint.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import asdict
from pathlib import Path

from tensorboardX import SummaryWriter

from learner.guide_learner import GuideBuffer, pool, read_snapshot, write_snapshot
from orchestration.guide_train import GuideCounters, GuideResult, judge_nodes, new_learner, restore_newest
from orchestration.stopping import StopRequest, stop_on_signals
from rllock.config import GuideTrainConfig
from rllock.errors import RLLockError
from rllock.files import checkpoint as ckpt
from rllock.files import orbax_io
from rllock.files.provenance import portable, portable_sessions, provenance
from rllock.search.guide import channels
from rllock.search.guide_checkpoint import guide_metadata, read_guide_metadata

log = logging.getLogger(__name__)

LOSS_EVERY = 10  # learner steps between the losses written to TensorBoard
JUDGE_EVERY = 250  # learner steps between held-out judgements (besides each checkpoint's): of every
# held-out node, as the buffer is in this process and does not change


def snapshot_paths(replay_from: str) -> list[Path]:
    """The snapshot files `--replay-from` names: a run folder stands for its `replay.npz`."""
    paths = []
    for source in filter(None, (s.strip() for s in replay_from.split(","))):
        path = Path(source)
        path = path / "replay.npz" if path.is_dir() else path
        if not path.is_file():
            raise RLLockError(f"--replay-from {source}: no replay snapshot there (a train-guide run or .npz)")
        paths.append(path)
    if not paths:
        raise RLLockError("--replay-from names no snapshot")
    return paths


def sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def made_by(path: Path) -> list[dict]:
    """The sessions of the run that made the snapshot at `path` (command, commit, machine, date): its
    run's checkpoint metadata, or for a kept snapshot (`keep_snapshot`) the record beside it."""
    record = path.with_suffix(".json")
    try:
        if path.name == "replay.npz" and ckpt.saved_steps(path.parent / "checkpoints"):
            return list(read_guide_metadata(ckpt.find_step_dir(path.parent)).get("sessions", []))
        if record.is_file():
            return list(json.loads(record.read_text()).get("sessions", []))
    except (OSError, json.JSONDecodeError, RLLockError) as exc:
        raise RLLockError(f"the record of replay snapshot {path} is unreadable: {exc}") from None
    return []


def load_pool(config: GuideTrainConfig) -> tuple[GuideBuffer, list[dict]]:
    """The pooled buffer of `config.replay_from` and a record of each snapshot in it: its path, states,
    SHA-256 and the sessions that made it."""
    paths = snapshot_paths(config.replay_from)
    snapshots = {str(p): read_snapshot(p) for p in paths}
    buffer = pool(snapshots, config.guide.window, channels(config.guide))
    record = [
        {
            "source": str(p),
            "states": len(snapshots[str(p)]["target"]),
            "sha256": sha256(p),
            "made_by": made_by(p),
        }
        for p in paths
    ]
    return buffer, record


def keep_snapshot(run: Path, out: Path) -> dict:
    """Keep the replay snapshot of the guide run in `run` at `out` (a compressed .npz) with the run's
    config, counters and sessions beside it (`out` with .json), made portable: the searches a guide
    learns from outlive the machine that made them (`--replay-from OUT`)."""
    doc = read_guide_metadata(ckpt.find_step_dir(run))
    snapshot = read_snapshot(run / "replay.npz")
    size = len(snapshot["target"])
    out.parent.mkdir(parents=True, exist_ok=True)
    write_snapshot(out, snapshot, compressed=True)
    record = {
        "run": portable(run),
        "states": size,
        "sha256": sha256(out),
        "config": doc["config"] | {"logdir": portable(doc["config"]["logdir"])},
        "counters": doc.get("counters", {}),
        "sessions": portable_sessions(doc.get("sessions", [])),
    }
    out.with_suffix(".json").write_text(json.dumps(record, indent=1) + "\n")
    return record


def train_offline(config: GuideTrainConfig, *, resume: bool = False) -> GuideResult:
    """`train_guide` for a config with `replay_from`, which has validated it."""
    run = _OfflineRun(config, time.monotonic(), resume)
    try:
        with stop_on_signals(run.stop):
            run.loop()
    finally:
        run.writer.close()
        run.manager.close()
    return GuideResult(
        run.learner.step,
        run.counters.searches,
        run.counters.solved,
        time.monotonic() - run.began,
        str(run.logdir),
        run.stop.requested,
        run.stop.signum,
    )


class _OfflineRun:
    def __init__(self, config: GuideTrainConfig, began: float, resume: bool):
        self.config, self.began, self.logdir = config, began, Path(config.logdir)
        self.buffer, self.replay = load_pool(config)
        self.learner = new_learner(config)
        self.counters, self.sessions = GuideCounters(states=self.buffer.size), []
        if resume:
            self._restore()
        self.sessions.append(provenance())
        log.info("%d states from %d snapshot(s): %s", self.buffer.size, len(self.replay), config.replay_from)
        self.logdir.mkdir(parents=True, exist_ok=True)
        self.writer = SummaryWriter(str(self.logdir), purge_step=self.learner.step if resume else None)
        self.manager = orbax_io.manager(self.logdir / "checkpoints", keep=3)
        self.stop = StopRequest()

    def _restore(self) -> None:
        doc = restore_newest(self.logdir, self.learner)
        if [r["sha256"] for r in doc.get("replay", [])] != [r["sha256"] for r in self.replay]:
            raise RLLockError(
                f"cannot resume {self.logdir}: its replay snapshots are not the ones it was trained on"
            )
        self.counters, self.sessions = GuideCounters(**doc["counters"]), list(doc.get("sessions", []))
        log.info("resuming %s at learner step %d", self.logdir, self.learner.step)

    def loop(self) -> None:
        config, learner = self.config, self.learner
        deadline, limit = self.began + 60 * config.minutes, config.max_learner_steps
        base, start, last_checkpoint = self.counters.seconds, time.monotonic(), time.monotonic()
        saved = learner.step if learner.step else None
        while (
            not self.stop.requested
            and time.monotonic() < deadline
            and (limit is None or learner.step < limit)
        ):
            value, rank = learner.update(self.buffer.sample(config.batch_size, learner.next_seed()))
            self.counters.seconds = base + time.monotonic() - start
            if learner.step % LOSS_EVERY == 0 or learner.step == 1:
                self.writer.add_scalar("losses/value", value, learner.step)
                self.writer.add_scalar("losses/siblings", rank, learner.step)
            if time.monotonic() - last_checkpoint >= 60 * config.checkpoint_minutes:
                self._checkpoint()
                saved, last_checkpoint = learner.step, time.monotonic()
            elif learner.step % JUDGE_EVERY == 0 and learner.step != limit:  # the last: its checkpoint's
                self._judge()
        if learner.step != saved:
            self._checkpoint()

    def _judge(self) -> None:
        judge_nodes(
            self.learner.guide,
            self.config.guide,
            lambda kept_out: self.buffer.nodes(kept_out, self.buffer.size, self.learner.step),
            self.writer,
            self.learner.step,
        )

    def _checkpoint(self) -> None:
        self._judge()
        doc = guide_metadata(self.config, self.learner.step, asdict(self.counters), self.sessions)
        orbax_io.save(self.manager, self.learner.step, self.learner.state(), doc | {"replay": self.replay})
        self.writer.flush()
        log.info("checkpoint at learner step %d", self.learner.step)
