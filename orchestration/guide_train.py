"""`rllock train-guide`: the guide network trained by the actor-learner loop (`rllock.orchestration.loop`).

Search actors (`rllock.actors.guide_actor`) each run the search solver on a curriculum task with the latest
weights version and push the children of a few states it left, labelled by rollouts, into the replay
buffer actor (`rllock.learner.guide_learner.GuideBuffer`); this process learns from the buffer (at most
`replay_ratio` sampled states per state produced), hands out a new weights version every
`publish_every` steps, writes TensorBoard events (with, at each checkpoint, how well it orders the
siblings of nodes held out of training: `rllock.learner.guide_learner.judge`) and keeps:
  LOGDIR/checkpoints/<step>/  the latest checkpoints (orbax: learner state + metadata)
  LOGDIR/replay.npz           the replay buffer, snapshotted with every checkpoint
With --replay-from it learns without searching, on the states of replay snapshots already made
(`rllock.orchestration.guide_offline`), judging every JUDGE_EVERY steps too. `--minutes` is a hard budget
(searches under way at its end are dropped). `rllock train-guide --resume LOGDIR` continues from the
newest readable checkpoint with its config, optimizer state, PRNG key, counters and replay buffer.
Ctrl-C and SIGTERM stop cleanly with a final checkpoint.
"""

from __future__ import annotations

import dataclasses
import logging
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from rllock.actors.guide_actor import SearchReport
from rllock.config import GuideConfig, GuideTrainConfig, from_json
from rllock.files import checkpoint as ckpt
from rllock.learner.guide_learner import judge
from rllock.orchestration.builder import GuideBuilder, OfflineGuideBuilder, run
from rllock.orchestration.loop import System
from rllock.orchestration.recorder import Recorder
from rllock.search.curriculum import edge_pieces
from rllock.search.guide_checkpoint import read_guide_metadata

log = logging.getLogger(__name__)

JUDGE_EVERY = 250  # learner steps between the judgements of a guide taught snapshots, besides each
# checkpoint's: it judges every held-out node, as its buffer is in this process and does not change


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


def train_guide(config: GuideTrainConfig, *, resume: bool = False) -> GuideResult:
    """Train the guide network, by searches (`config.replay_from`: on replay snapshots already made)."""
    began = time.monotonic()
    builder = OfflineGuideBuilder(config) if config.replay_from else GuideBuilder(config)
    offline = bool(config.replay_from)
    loop = run(
        builder, lambda system: SearchWatch(builder, system, offline=offline), resume=resume, began=began
    )
    return GuideResult(
        builder.learner.step,
        builder.totals.searches,
        builder.totals.solved,
        time.monotonic() - began,
        str(builder.logdir),
        loop.stop.requested,
        loop.stop.signum,
    )


def judge_nodes(
    params: dict, config: GuideConfig, nodes_of: Callable[[bool], dict], recorder: Recorder, step: int
) -> None:
    """How well the network orders siblings on nodes it never trained on, against nodes it trained on
    and against the lookahead share alone (`rllock.learner.guide_learner.judge`; `nodes_of(True)` gives
    held-out nodes, `nodes_of(False)` trained-on ones), in TensorBoard and the log."""
    found = {}
    for name, kept_out in (("heldout", True), ("trained", False)):
        nodes = nodes_of(kept_out)
        if not len(nodes["target"]):
            return
        found[name] = judge(params, config, nodes)
        recorder.scalars({f"{name}/{key}": value for key, value in found[name].items()}, step)
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


class SearchWatch:
    """What a guide run watches beside the loop (`rllock.orchestration.loop.Monitor`): each search, in the log
    and TensorBoard, the K `--edge` moves, and the judgement of the guide at every checkpoint (and, taught
    snapshots `offline`, every JUDGE_EVERY learner steps)."""

    def __init__(self, builder: GuideBuilder, system: System, *, offline: bool):
        self.builder, self.config, self.learner = builder, builder.config, builder.learner
        self.totals, self.recorder = builder.totals, system.recorder
        self.offline, self.judged = offline, -1  # the learner step judged last

    def count(self, report: SearchReport) -> None:
        t, step = self.totals, self.learner.step
        assert report.buffer is not None
        log.info(
            "search %d (%s, %s): %s, %d/%d placed, %d states labelled (mean %.2f) in %.0f s",
            t.searches,
            report.task,
            "guided" if report.guided else "plain",
            "solved" if report.solved else "not solved",
            report.placed,
            report.pieces - 1,
            report.states,
            report.winning,
            report.seconds,
        )
        per_search: dict[str, float] = {}
        if report.cell in t.edge:
            t.edge[report.cell] = edge_pieces(
                t.edge[report.cell], report.solved, self.builder.cells[report.cell]
            )
            tag = re.sub(r"[^-/\w.]", "_", report.cell)  # as TensorBoard would, without its warning
            per_search[f"edge/{tag}"] = t.edge[report.cell]
        per_search["search/solved"] = float(report.solved)
        per_search["search/placed_share"] = report.placed / max(report.pieces - 1, 1)
        if report.states:
            per_search["probes/mean_label"] = report.winning
        self.recorder.scalars(per_search, t.searches)
        per_step: dict[str, float] = {
            "buffer/size": report.buffer.size,
            "buffer/solved_states": report.buffer.successes,
        }
        if t.guided:
            per_step["search/guided_solve_rate"] = t.guided_solved / t.guided
        if t.searches > t.guided:
            per_step["search/plain_solve_rate"] = (t.solved - t.guided_solved) / (t.searches - t.guided)
        self.recorder.scalars(per_step, step)

    def periodic(self, now: float) -> None:
        step, limit = self.learner.step, self.config.max_learner_steps
        # The last step is judged by its checkpoint.
        if self.offline and step % JUDGE_EVERY == 0 and step not in (limit, self.judged):
            self._judge()

    def reserve(self) -> float:
        return 0.0

    def score(self) -> None:
        return None

    def checkpointed(self) -> None:
        self._judge()
        t = self.totals
        if self.offline:  # no searches to count
            log.info("checkpoint at learner step %d", self.learner.step)
        else:
            log.info(
                "checkpoint at learner step %d (%d searches, %d solved)",
                self.learner.step,
                t.searches,
                t.solved,
            )

    def final(self, now: float, *, stopped: bool) -> None:
        pass

    def _judge(self) -> None:
        self.judged = self.learner.step
        judge_nodes(self.learner.guide, self.config.guide, self.builder.nodes, self.recorder, self.judged)
