"""`rllock train-guide`: the guide network trained by our actor-learner system.

Search actors (`actors.guide_actor`) each run the search solver on a curriculum task with the latest
weights version and push the children of a few states it left, labelled by rollouts, into the replay
buffer actor
(`learner.guide_learner.GuideBuffer`); this process learns from the buffer (at most `replay_ratio`
sampled states per state produced), hands out a new weights version every `publish_every` steps, writes
TensorBoard events (with, at each checkpoint, how well it orders the siblings of nodes held out of
training: `learner.guide_learner.judge`) and keeps:
  LOGDIR/checkpoints/<step>/  the latest checkpoints (orbax: learner state + metadata)
  LOGDIR/replay.npz           the replay buffer, snapshotted with every checkpoint
`--minutes` is a hard budget (searches under way at its end are dropped). `rllock train-guide --resume
LOGDIR` continues from the newest readable checkpoint with its config, optimizer state, PRNG key,
counters and replay buffer. Ctrl-C and SIGTERM stop cleanly with a final checkpoint.
"""

from __future__ import annotations

import dataclasses
import logging
import re
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import jax
import ray
from tensorboardX import SummaryWriter

from actors.guide_actor import GuideActor, SearchReport
from actors.selfplay import actor_env
from learner.guide_learner import GuideBuffer, GuideLearner, judge
from orchestration.pool import Calls, on_driver_node, start_ray
from orchestration.stopping import StopRequest, stop_on_signals
from rllock.config import GuideConfig, GuideTrainConfig, from_json
from rllock.core.env import Task
from rllock.errors import RLLockError
from rllock.files import checkpoint as ckpt
from rllock.files import orbax_io
from rllock.files.provenance import provenance
from rllock.search.curriculum import edge_pieces, named_tasks
from rllock.search.guide import channels
from rllock.search.guide_checkpoint import guide_metadata, read_guide_metadata

log = logging.getLogger(__name__)

JUDGED_NODES = 200  # nodes held out, and as many trained on, judged at each checkpoint


@dataclass
class GuideCounters:
    """Run totals, and where `--edge` has moved each cell's K, that survive a resume."""

    searches: int = 0
    solved: int = 0
    guided: int = 0
    guided_solved: int = 0
    states: int = 0
    seconds: float = 0.0
    version: int = 0
    edge: dict[str, int] = field(default_factory=dict)  # `--edge`: each cell's K now, by its label

    def add(self, report: SearchReport) -> None:
        self.searches += 1
        self.solved += report.solved
        self.guided += report.guided
        self.guided_solved += report.guided and report.solved
        self.states += report.states


@dataclass(frozen=True)
class GuideResult:
    steps: int
    searches: int
    solved: int
    seconds: float
    logdir: str
    interrupted: bool
    stop_signal: int | None


def resume_config(
    logdir: Path, minutes: float, actors: int, address: str | None, max_learner_steps: int | None = None
) -> GuideTrainConfig:
    """The config of the guide run in `logdir`, from its newest readable checkpoint, with `minutes` more
    and a new step limit (none: only the minutes), on this machine: `actors` and `address` are where the
    run goes on (a run begun on a workstation goes on on a laptop), not what it learns."""
    doc = ckpt.newest_readable(logdir, read_guide_metadata)
    return dataclasses.replace(
        from_json(GuideTrainConfig, doc["config"]),
        logdir=str(logdir),
        minutes=minutes,
        max_learner_steps=max_learner_steps,
        actors=actors,
        address=address,
    )


def judge_nodes(
    params: dict, config: GuideConfig, nodes_of: Callable[[bool], dict], writer: SummaryWriter, step: int
) -> None:
    """How well the network orders siblings on nodes it never trained on, against nodes it trained on
    and against the lookahead share alone (`learner.guide_learner.judge`; `nodes_of(True)` gives held-out
    nodes, `nodes_of(False)` trained-on ones), in TensorBoard and the log."""
    found = {}
    for name, kept_out in (("heldout", True), ("trained", False)):
        nodes = nodes_of(kept_out)
        if not len(nodes["target"]):
            return
        found[name] = judge(params, config, nodes)
        for key, value in found[name].items():
            writer.add_scalar(f"{name}/{key}", value, step)
    held, trained = found["heldout"], found["trained"]
    log.info(
        "siblings ordered rightly on held-out nodes: %.1f%% by the guide, %.1f%% by the search's own "
        "order, %.1f%% by the lookahead share (%d pairs); on nodes it trains on: %.1f%%",
        100 * held["siblings"],
        100 * held["search_order"],
        100 * held["share"],
        held["pairs"],
        100 * trained["siblings"],
    )


def new_learner(config: GuideTrainConfig) -> GuideLearner:
    """The run's learner at its initial weights, from the run's seed."""
    return GuideLearner(
        config.guide,
        config.guide_learning_rate,
        jax.random.PRNGKey(config.seed),
        config.rank_weight,
        config.weight_average,
    )


def restore_newest(logdir: Path, learner: GuideLearner) -> dict:
    """Load the newest readable checkpoint of the guide run in `logdir` into `learner`; its metadata."""

    def restore(step_dir: Path) -> dict:
        doc = read_guide_metadata(step_dir)
        learner.load_state(orbax_io.restore_like(step_dir, learner.state()))
        return doc

    return ckpt.newest_readable(logdir, restore)


def train_guide(config: GuideTrainConfig, *, resume: bool = False) -> GuideResult:
    """Train the guide network (`config.replay_from`: on replay snapshots already made, without
    searching: `orchestration.guide_offline`)."""
    config.validate()
    logdir = Path(config.logdir)
    if not resume and ckpt.saved_steps(logdir / "checkpoints"):
        raise RLLockError(f"{logdir} already holds a guide run; resume it with --resume {logdir}")
    if config.replay_from:
        from orchestration.guide_offline import train_offline  # it builds on this module

        return train_offline(config, resume=resume)
    named = named_tasks(config.cells) if config.cells else []  # a bad cell is one line here
    began = time.monotonic()
    started = start_ray(config.address)  # before JAX's threads: Ray forks
    try:
        run = _GuideRun(config, began, resume, named)
        try:
            with stop_on_signals(run.stop):
                return run.loop()
        finally:
            run.writer.close()
    finally:
        if started:
            ray.shutdown()


def _start_buffer(config: GuideTrainConfig) -> Any:
    """The replay buffer actor, on the driver's node (it snapshots into the run's folder). Its handle is
    Any: Ray types an ActorHandle's methods as Never."""
    return (
        ray.remote(num_cpus=0)(GuideBuffer)
        .options(scheduling_strategy=on_driver_node())
        .remote(config.buffer_capacity, config.guide.window, channels(config.guide))
    )


class _GuideRun:
    def __init__(self, config: GuideTrainConfig, began: float, resume: bool, named: list[Task]):
        self.config, self.began = config, began
        self.logdir = Path(config.logdir)
        self.learner = new_learner(config)
        self.counters, self.sessions = GuideCounters(), []
        if resume:
            self._restore()
        self.cells = {task.shape_name: task for task in named}
        if config.edge and not self.counters.edge:
            self.counters.edge = {label: task.pieces for label, task in self.cells.items()}
        self.sessions.append(provenance())
        self.logdir.mkdir(parents=True, exist_ok=True)
        self.writer = SummaryWriter(str(self.logdir), purge_step=self.learner.step if resume else None)
        self.manager = orbax_io.manager(self.logdir / "checkpoints", keep=3)
        self.buffer = _start_buffer(config)
        snapshot = self.logdir / "replay.npz"
        self.available = 0  # states in the buffer, as the last search's push (or the restore) reported
        if resume and snapshot.exists():
            self.available = ray.get(self.buffer.restore.remote(str(snapshot)))
            log.info("replay buffer restored: %d states", self.available)
        self.stop = StopRequest()
        self.saved: tuple[int, int] | None = None  # (learner step, searches) of the last checkpoint

    def _restore(self) -> None:
        doc = restore_newest(self.logdir, self.learner)
        self.counters = GuideCounters(**doc.get("counters", {}))
        self.sessions = list(doc.get("sessions", []))
        log.info(
            "resuming %s at learner step %d (%d searches so far)",
            self.logdir,
            self.learner.step,
            self.counters.searches,
        )

    def _actors(self) -> int:
        if self.config.actors:
            return self.config.actors
        return max(1, int(ray.cluster_resources().get("CPU", 1)) - 1)

    def _new_actor(self) -> Any:
        self.started += 1
        seed = self.config.seed * 1000 + self.started + self.counters.searches
        options = dict(
            num_cpus=1, max_restarts=-1, max_task_retries=-1, runtime_env={"env_vars": actor_env(1)}
        )
        return GuideActor.options(**options).remote(seed, self.config)  # type: ignore[attr-defined]

    def _hand(self, actor: Any) -> None:
        """Give `actor` its next search, with the newest weights."""
        edge = dict(self.counters.edge) or None
        self.calls.submit(
            actor, actor.run.remote(self.weights, self.counters.version, self.buffer, edge), None
        )

    def loop(self) -> GuideResult:
        c, config = self.counters, self.config
        deadline = self.began + 60 * config.minutes
        self.started, self.calls = 0, Calls()
        self.weights = [ray.put(jax.device_get(self.learner.guide))]
        for _ in range(self._actors()):
            self._hand(self._new_actor())
        log.info(
            "training the guide: %d search actor(s) for %g min; logs in %s",
            self.started,
            config.minutes,
            self.logdir,
        )
        base, start, last_checkpoint = c.seconds, time.monotonic(), time.monotonic()
        while not self.stop.requested and time.monotonic() < deadline and not self._reached_max():
            self._turn(deadline)
            c.seconds = base + time.monotonic() - start
            if time.monotonic() - last_checkpoint >= 60 * config.checkpoint_minutes:
                self._checkpoint()
                last_checkpoint = time.monotonic()
        self.calls.cancel_all()  # the budget is a hard limit: searches under way are dropped
        if (self.learner.step, c.searches) != self.saved:  # else the last periodic one holds it all
            self._checkpoint()
        elapsed = time.monotonic() - self.began
        return GuideResult(
            self.learner.step,
            c.searches,
            c.solved,
            elapsed,
            str(self.logdir),
            self.stop.requested,
            self.stop.signum,
        )

    def _reached_max(self) -> bool:
        limit = self.config.max_learner_steps
        return limit is not None and self.learner.step >= limit

    def _turn(self, deadline: float) -> None:
        """Collect finished searches (waiting up to 1 s for one when the learner may not step), hand their
        actors the next, then take a learner step if the replay ratio allows."""
        c, config = self.counters, self.config
        can_learn = (
            self.available >= config.batch_size
            and self.learner.step * config.batch_size < config.replay_ratio * c.states
        )
        done, failed = self.calls.wait(0.0 if can_learn else min(1.0, max(0.0, deadline - time.monotonic())))
        for _, _, why in failed:
            log.error("search actor failed for good (%s); a new actor takes its place", why)
            self._hand(self._new_actor())
        for actor, _, report in done:
            self._count(report)
            self._hand(actor)
        if can_learn and self._learn():
            self.weights = [ray.put(jax.device_get(self.learner.guide))]

    def _count(self, report: SearchReport) -> None:
        c = self.counters
        c.add(report)
        assert report.buffer is not None
        self.available = report.buffer.size
        log.info(
            "search %d (%s, %s): %s, %d/%d placed, %d states labelled (mean %.2f) in %.0f s",
            c.searches,
            report.task,
            "guided" if report.guided else "plain",
            "solved" if report.solved else "not solved",
            report.placed,
            report.pieces - 1,
            report.states,
            report.winning,
            report.seconds,
        )
        if report.cell in c.edge:
            c.edge[report.cell] = edge_pieces(c.edge[report.cell], report.solved, self.cells[report.cell])
            tag = re.sub(r"[^-/\w.]", "_", report.cell)  # as TensorBoard would, without its warning
            self.writer.add_scalar(f"edge/{tag}", c.edge[report.cell], c.searches)
        step = self.learner.step
        self.writer.add_scalar("search/solved", float(report.solved), c.searches)
        self.writer.add_scalar("search/placed_share", report.placed / max(report.pieces - 1, 1), c.searches)
        if report.states:
            self.writer.add_scalar("probes/mean_label", report.winning, c.searches)
        self.writer.add_scalar("buffer/size", report.buffer.size, step)
        self.writer.add_scalar("buffer/solved_states", report.buffer.successes, step)
        if c.guided:
            self.writer.add_scalar("search/guided_solve_rate", c.guided_solved / c.guided, step)
        plain = c.searches - c.guided
        if plain:
            self.writer.add_scalar("search/plain_solve_rate", (c.solved - c.guided_solved) / plain, step)

    def _learn(self) -> bool:
        sample = ray.get(self.buffer.sample.remote(self.config.batch_size, self.learner.next_seed()))
        value, rank = self.learner.update(sample)
        if self.learner.step % 10 == 0 or self.learner.step == 1:
            self.writer.add_scalar("losses/value", value, self.learner.step)
            self.writer.add_scalar("losses/siblings", rank, self.learner.step)
        if self.learner.step % self.config.publish_every == 0:
            self.counters.version += 1
            return True
        return False

    def _judge(self) -> None:
        judge_nodes(
            self.learner.guide,
            self.config.guide,
            lambda kept_out: ray.get(self.buffer.nodes.remote(kept_out, JUDGED_NODES, self.learner.step)),
            self.writer,
            self.learner.step,
        )

    def _checkpoint(self) -> None:
        self._judge()
        ray.get(self.buffer.snapshot.remote(str(self.logdir / "replay.npz")))
        doc = guide_metadata(self.config, self.learner.step, asdict(self.counters), self.sessions)
        orbax_io.save(self.manager, self.learner.step, self.learner.state(), doc)
        self.writer.flush()
        self.saved = (self.learner.step, self.counters.searches)
        log.info(
            "checkpoint at learner step %d (%d searches, %d solved)",
            self.learner.step,
            self.counters.searches,
            self.counters.solved,
        )
