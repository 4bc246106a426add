"""`rllock bench ablation`: the paper's Table 1 for our three methods, from trained checkpoints.

The checkpoints are training runs in `ROOT/<method>/<task>/` (as `scripts/train_ablation.sh` makes them:
`rl-lock`, `rl-lock-action`, `ppo`; tasks named like the shipped checkpoints, `cube4-k7`). For each
one: the training time its checkpoint records, and the paper's inference protocol (batches of 64
episodes until 5 valid assemblies or the time limit), time per valid assembly or "none within the
limit". The paper's figures (minutes, RTX 5090 workstation) stand beside them.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

from rllock.config import METHODS
from rllock.errors import RLLockError
from rllock.files.checkpoint import open_checkpoint
from rllock.orchestration.bench.paper import PaperTask, parse_paper_tasks
from rllock.search.inference import generate, load_policy

log = logging.getLogger(__name__)

# Table 1 of the paper, minutes: task -> method -> (training, inference per valid or None: none in 60 min).
PAPER_TABLE: dict[str, dict[str, tuple[float, float | None]]] = {
    "cube4-k7": {"ppo": (29.40, None), "rl-lock-action": (62.40, 0.01), "rl-lock": (33.00, 0.05)},
    "cube4-k8": {"ppo": (21.60, None), "rl-lock-action": (83.40, None), "rl-lock": (49.20, 0.47)},
    "cube4-k9": {"ppo": (29.40, None), "rl-lock-action": (114.00, None), "rl-lock": (35.40, 1.22)},
    "cube5-k13": {"ppo": (76.80, None), "rl-lock-action": (165.60, 0.01), "rl-lock": (66.60, 0.60)},
    "cube5-k14": {"ppo": (85.20, None), "rl-lock-action": (132.00, None), "rl-lock": (80.40, 0.84)},
    "cube5-k16": {"ppo": (76.20, None), "rl-lock-action": (148.80, None), "rl-lock": (94.80, 1.68)},
    "cube6-k20": {"ppo": (59.40, None), "rl-lock-action": (144.60, None), "rl-lock": (63.00, 2.86)},
    "cube6-k22": {"ppo": (91.20, None), "rl-lock-action": (195.00, None), "rl-lock": (74.40, 3.46)},
    "cube6-k25": {"ppo": (107.40, None), "rl-lock-action": (100.20, None), "rl-lock": (90.60, 4.87)},
}


def parse_ablation_tasks(spec: str | None) -> list[PaperTask]:
    """'cube4-k7,cube5-k13' -> those tasks; None -> 4^3 K=7/8/9 and 5^3 K=13, where the paper's
    baselines found something or came closest."""
    tasks = parse_paper_tasks(spec or "cube4-k7,cube4-k8,cube4-k9,cube5-k13")
    for task in tasks:
        if task.name not in PAPER_TABLE:
            raise RLLockError(f"the ablation covers the nine cube tasks, not {task.name}")
    return tasks


@dataclass(frozen=True)
class AblationCell:
    method: str
    task: str
    checkpoint: str | None  # None: no run of this method for this task under the root
    training_minutes: float | None
    valid: int
    episodes: int
    seconds: float

    @property
    def minutes_per_valid(self) -> float | None:
        return self.seconds / self.valid / 60 if self.valid else None


def ablation_cell(
    root: Path, method: str, task: PaperTask, *, count: int, batch: int, time_limit: float, seed: int
) -> AblationCell:
    run = root / method / task.name
    if not run.is_dir():
        return AblationCell(method, task.name, None, None, 0, 0, 0.0)
    checkpoint = open_checkpoint(run)
    minutes = checkpoint.metadata.counters.get("seconds", 0.0) / 60
    start = time.perf_counter()
    policy = load_policy(checkpoint)
    if policy.method != method or policy.task.pieces != task.pieces:
        raise RLLockError(
            f"{run} holds a {policy.method} checkpoint for K={policy.task.pieces}, "
            f"not {method} for {task.name}"
        )
    result = generate(policy, count=count, batch=batch, time_limit=time_limit, seed=seed, progress=False)
    cell = AblationCell(
        method, task.name, str(run), minutes, result.valid, result.episodes, time.perf_counter() - start
    )
    log.info(
        "%s %s: %d valid of %d episodes in %.1f s", task.name, method, cell.valid, cell.episodes, cell.seconds
    )
    return cell


def format_ablation_table(cells: list[AblationCell], time_limit: float, command: str) -> str:
    """Table 1's layout: per task, training and inference minutes for each method, ours and the paper's."""
    by = {(c.task, c.method): c for c in cells}
    tasks = list(dict.fromkeys(c.task for c in cells))
    order = ("ppo", "rl-lock-action", "rl-lock")
    assert set(order) == set(METHODS)

    def ours(c: AblationCell | None) -> str:
        if c is None or c.checkpoint is None:
            return "not trained | -"
        per_valid = c.minutes_per_valid
        infer = f"none in {time_limit / 60:.0f} min" if per_valid is None else f"{per_valid:.2f}"
        return f"{c.training_minutes:.1f} | {infer}"

    def paper(task: str, method: str) -> str:
        train, infer = PAPER_TABLE[task][method]
        return f"{train:.1f} | {'none in 60 min' if infer is None else f'{infer:.2f}'}"

    header = " | ".join(f"{m} train | {m} infer" for m in order)
    lines = [
        f"    {command}",
        "",
        "Minutes. Train: the run's training time. Infer: time per valid assembly (batches of 64 until 5 "
        f"valid, {time_limit:.0f} s limit; load and compile included). Paper: Table 1 (RTX 5090).",
        "",
        f"| task | {header} |",
        "|---|" + "---|" * (2 * len(order)),
    ]
    for task in tasks:
        lines.append(f"| {task} (ours) | " + " | ".join(ours(by.get((task, m))) for m in order) + " |")
        lines.append(f"| {task} (paper) | " + " | ".join(paper(task, m) for m in order) + " |")
    return "\n".join(lines) + "\n"
