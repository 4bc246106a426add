"""`rllock bench transfer`: a multi-task checkpoint on tasks it may never have seen, four ways.

For each task, the paper's protocol (batches of 64 episodes until 5 valid assemblies or the time limit):
  zero-shot   the multi-task checkpoint, not trained further;
  untrained   the same network and search with fresh weights;
  per task    the shipped single-task checkpoint of that task, where one is shipped (e.g. cube4-k9);
  solver      the search solver.
Each row says whether the task's shape was one of the checkpoint's training shapes (random training
shapes are fresh draws, so a named shape outside the spec was never seen). Times are wall clock per
valid assembly, loading and compiling included (`rllock.orchestration.bench.paper`).
"""

from __future__ import annotations

from dataclasses import dataclass

from rllock.core.env import Task, make_task
from rllock.core.shapes import grid_sha256
from rllock.errors import RLLockError
from rllock.files.checkpoint import Checkpoint, Metadata, open_checkpoint, shipped_names
from rllock.orchestration.bench.arms import (
    Arm,
    ArmProtocol,
    arm_cell,
    arm_json,
    policy_arm,
    protocol_note,
    solver_arm,
    warm_process,
)
from rllock.orchestration.bench.specs import parse_list
from rllock.search.inference import load_policy, untrained_like, with_simulations

# Held-out shapes for a generalist trained on cubes, boxes and random shapes: not cubes, 144-168 voxels,
# on the paper's 8^3 canvas, two piece counts each.
HELD_OUT = "sofa:12,sofa:16,cubeweird:12,cubeweird:16,ring:12,ring:15,stairs:12,stairs:16,tube:12,tube:16"


@dataclass(frozen=True)
class TransferTask:
    shape: str
    pieces: int

    @property
    def name(self) -> str:
        """The shipped single-task checkpoint's name for this task (e.g. cube4-k9)."""
        return f"{self.shape}-k{self.pieces}"


def parse_transfer_tasks(spec: str | None) -> list[TransferTask]:
    """'sofa:12,cube4:9' or the paper's names ('cube4-k9'); None: the held-out set (`HELD_OUT`)."""
    return parse_list(spec or HELD_OUT, [], _transfer_task, "--tasks")


def _transfer_task(item: str) -> TransferTask:
    if "-k" in item and ":" not in item:
        shape, _, k = item.rpartition("-k")
    else:
        shape, _, k = item.rpartition(":")
    if not shape or not k.isdigit():
        raise RLLockError(f"bad task {item!r}: use SHAPE:K (e.g. sofa:12) or a name like cube4-k9")
    return TransferTask(shape, int(k))


@dataclass(frozen=True)
class TransferRow:
    task: TransferTask
    seen: bool  # the shape is one of the checkpoint's training shapes
    zero_shot: Arm
    untrained: Arm
    per_task: Arm | None  # None: no shipped checkpoint for this task
    solver: Arm
    simulations: int  # per decision, in the zero-shot and untrained arms
    per_task_simulations: int | None


def multitask_checkpoint(checkpoint: str | Checkpoint) -> Checkpoint:
    """A multi-task checkpoint, opened; any other is a clear error."""
    opened = open_checkpoint(checkpoint)
    if not opened.metadata.multitask:
        raise RLLockError(
            f"checkpoint {checkpoint} was trained for one task; bench transfer needs --tasks runs"
        )
    return opened


def bench_transfer_task(
    checkpoint: str | Checkpoint,
    task: TransferTask,
    *,
    count: int,
    batch: int,
    time_limit: float,
    seed: int,
    simulations: int | None = None,
) -> TransferRow:
    """One row; `simulations` (None: the checkpoint's own) sets the search of the zero-shot and untrained
    arms, the per-task checkpoint searches as it was trained."""
    opened = multitask_checkpoint(checkpoint)
    warm_process(task.shape, task.pieces)
    t = make_task(task.shape, task.pieces, opened.metadata.removal)
    seen = trained_on(opened.metadata, t)
    protocol = ArmProtocol(count=count, batch=batch, time_limit=time_limit, seed=seed)
    zero, policy = policy_arm(lambda: with_simulations(load_policy(opened, t), simulations), **protocol)
    untrained, _ = policy_arm(lambda: untrained_like(policy, seed), **protocol)
    per_task, own = None, None
    if task.name in shipped_names():
        shipped = open_checkpoint(task.name)
        per_task, own = policy_arm(lambda: load_policy(shipped, t), **protocol)
    solver = solver_arm(t, count=count, time_limit=time_limit, seed=seed)
    own_simulations = None if own is None else own.mcts.simulations
    return TransferRow(
        task, seen, zero, untrained, per_task, solver, policy.mcts.simulations, own_simulations
    )


def trained_on(meta: Metadata, task: Task) -> bool:
    """Whether `task`'s shape is one of the named training shapes of a multi-task checkpoint."""
    return grid_sha256(task.topology.grid) in meta.task["shapes_sha256"]


def row_json(row: TransferRow) -> dict:
    arm = arm_json
    return {
        "task": f"{row.task.shape}:{row.task.pieces}",
        "seen_in_training": row.seen,
        "zero_shot": arm(row.zero_shot),
        "untrained": arm(row.untrained),
        "per_task": arm(row.per_task),
        "solver": arm(row.solver),
        "simulations": {"zero_shot": row.simulations, "per_task": row.per_task_simulations},
        "zero_shot_over_untrained": ratio(row.zero_shot, row.untrained),
        "zero_shot_over_per_task": ratio(row.zero_shot, row.per_task),
    }


def ratio(a: Arm, b: Arm | None) -> str | None:
    """a's time per valid over b's; '<= x' when only b found nothing (b needs more than its seconds per
    valid); None when a found nothing or b is missing."""
    if b is None or a.time_per_valid_s is None:
        return None
    if b.time_per_valid_s is None:
        return f"<= {a.time_per_valid_s / b.seconds:.2f}"
    return f"{a.time_per_valid_s / b.time_per_valid_s:.2f}"


def simulations(row: TransferRow) -> str:
    """The table's simulations cell: the zero-shot and untrained arms', then the per-task checkpoint's."""
    own = "" if row.per_task_simulations is None else f" / {row.per_task_simulations}"
    return f"{row.simulations}{own}"


def format_transfer_table(rows: list[TransferRow], protocol: dict, command: str) -> str:
    arm = arm_cell
    lines = [
        f"    {command}",
        "",
        f"Seconds per valid assembly (valid found in brackets; {protocol_note(**protocol)}), loading and "
        "compiling included.",
        "",
        "| task | shape in training | simulations | zero-shot | untrained | zero-shot / untrained "
        "| per-task checkpoint | zero-shot / per-task | search solver |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r.task.shape} K={r.task.pieces} | {'yes' if r.seen else 'no'} | {simulations(r)} | "
            f"{arm(r.zero_shot)} | "
            f"{arm(r.untrained)} | {ratio(r.zero_shot, r.untrained) or '-'} | {arm(r.per_task)} | "
            f"{ratio(r.zero_shot, r.per_task) or '-'} | {arm(r.solver)} |"
        )
    return "\n".join(lines) + "\n"
