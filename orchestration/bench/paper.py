"""`rllock bench paper`: the paper's tasks, each run three ways under the paper's protocol.

For each task (a shipped checkpoint name such as `cube6-k25`): batches of 64 episodes until 5 valid
assemblies or the time limit, with the shipped checkpoint and with the same search untrained, then the
search solver for 5 assemblies under the same limit. Times are wall clock divided by the valid
assemblies found. Each network arm includes compiling its own search, and the trained arm loading its
checkpoint; what any arm would pay once per process (the sampler's compiled code, JAX's start) is paid
before the first arm, so that running first costs no arm anything. The paper's figures (Table 1, RTX 5090
workstation) stand beside them.

Each network arm also says how it started (`rllock.orchestration.bench.arms.Arm.cache`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import jax

from rllock.config import MCTSConfig, NetConfig
from rllock.core.env import make_task
from rllock.errors import RLLockError
from rllock.files.checkpoint import shipped_names
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
from rllock.orchestration.bench.solve import PAPER_MINUTES
from rllock.orchestration.bench.specs import parse_list
from rllock.search.inference import Policy, load_policy, untrained_like
from rllock.search.network import fit_canvas, init_params

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PaperTask:
    name: str  # the shipped checkpoint's name
    shape: str
    pieces: int
    in_table: bool  # in the paper's Table 1 (Ring and Sofa appear only in figures, without times)
    paper_rllock_s: float | None  # the paper's RL-Lock inference time per valid assembly
    paper_desia_s: float | None  # DESIA's; None in Table 1: nothing valid within 60 minutes


def _paper_tasks() -> dict[str, PaperTask]:
    tasks = {}
    for (size, k), (rl, desia) in PAPER_MINUTES.items():
        name = f"cube{size}-k{k}"
        tasks[name] = PaperTask(name, f"cube{size}", k, True, rl * 60, None if desia is None else desia * 60)
    tasks["ring-k15"] = PaperTask("ring-k15", "ring", 15, False, None, None)
    tasks["sofa-k19"] = PaperTask("sofa-k19", "sofa", 19, False, None, None)
    return tasks


PAPER_TASKS = _paper_tasks()


def parse_paper_tasks(spec: str | None) -> list[PaperTask]:
    """'cube4-k9,sofa-k19' -> those tasks; None -> all eleven."""
    return parse_list(spec, list(PAPER_TASKS.values()), _paper_task, "--tasks")


def _paper_task(name: str) -> PaperTask:
    if name not in PAPER_TASKS:
        raise RLLockError(f"unknown task {name!r}: the paper's tasks are {', '.join(PAPER_TASKS)}")
    return PAPER_TASKS[name]


@dataclass(frozen=True)
class PaperRow:
    task: PaperTask
    checkpoint: str | None  # None: nothing shipped under the task's name
    step: int | None
    trained: Arm | None
    untrained: Arm
    solver: Arm


def _untrained_policy(task: PaperTask, seed: int) -> Policy:
    """The untrained arm where nothing is shipped: the default network and search for the task."""
    t = make_task(task.shape, task.pieces)
    net = fit_canvas(t, NetConfig())
    params = init_params(net, jax.random.PRNGKey(seed))
    return Policy(t, net, MCTSConfig(), "rl-lock", params, f"untrained ({seed})", 0)


def bench_paper_task(task: PaperTask, *, count: int, batch: int, time_limit: float, seed: int) -> PaperRow:
    warm_process(task.shape, task.pieces)
    protocol = ArmProtocol(count=count, batch=batch, time_limit=time_limit, seed=seed)
    shipped = task.name in shipped_names()
    trained = None
    if shipped:
        trained, policy = policy_arm(lambda: load_policy(task.name), **protocol)
        untrained, _ = policy_arm(lambda: untrained_like(policy, seed), **protocol)
    else:
        untrained, _ = policy_arm(lambda: _untrained_policy(task, seed), **protocol)
    solver = solver_arm(make_task(task.shape, task.pieces), count=count, time_limit=time_limit, seed=seed)
    return PaperRow(
        task,
        task.name if shipped else None,
        policy.step if shipped else None,
        trained,
        untrained,
        solver,
    )


def row_json(row: PaperRow) -> dict:
    arm = arm_json
    return {
        "task": row.task.name,
        "shape": row.task.shape,
        "pieces": row.task.pieces,
        "checkpoint": row.checkpoint,
        "step": row.step,
        "trained": arm(row.trained),
        "untrained": arm(row.untrained),
        "solver": arm(row.solver),
        "paper_rllock_s": row.task.paper_rllock_s,
        "paper_desia_s": row.task.paper_desia_s,
    }


def starts(row: PaperRow) -> str:
    """The table's start-up cell: how the trained and the untrained arm started."""
    return f"{row.trained.cache if row.trained else '-'} / {row.untrained.cache}"


def format_paper_table(rows: list[PaperRow], protocol: dict, command: str) -> str:
    """The markdown table: seconds per valid assembly, with the valid count, beside the paper's."""
    arm = arm_cell

    def paper(task: PaperTask, v: float | None) -> str:
        if not task.in_table:
            return "-"
        return "none in 3600" if v is None else f"{v:.1f}"

    lines = [
        f"    {command}",
        "",
        f"Seconds per valid assembly (valid found in brackets; {protocol_note(**protocol)}). Trained: the "
        "shipped checkpoint, load and compile included. Start (trained / untrained): cold, the arm compiled "
        "programs JAX's persistent cache did not hold; warm, the cache held them; off, no cache. The tree "
        "search is compiled either way (JAX does not cache a program with host callbacks).",
        "",
        "| task | trained | untrained | search solver | start | paper RL-Lock | paper DESIA |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r.task.name} | {arm(r.trained)} | {arm(r.untrained)} | {arm(r.solver)} | {starts(r)} | "
            f"{paper(r.task, r.task.paper_rllock_s)} | {paper(r.task, r.task.paper_desia_s)} |"
        )
    return "\n".join(lines) + "\n"
