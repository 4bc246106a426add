"""`rllock bench guide`: seconds to the first valid assembly, the search solver against the same search
guided by a guide network, and guided by the same network untrained (learning is the cause), side by
side on the same seeds, one core a search.

A cell is SHAPE:K or SHAPE:K:path (a shape name, a .puz/.vol/.npy file, or a mesh with @RESOLUTION:
bunny.stl@24:40). Each arm of a cell runs each seed once; the table gives each seed's seconds, or none
within the limit with the most pieces placed, and the median; the ratio is solver over guided medians
(a time limit stands for an unsolved seed, so a ratio with unsolved seeds is a bound).
"""

from __future__ import annotations

import logging
import statistics
from dataclasses import dataclass

from rllock.core.env import initial_state
from rllock.orchestration.bench.arms import warm_process
from rllock.orchestration.bench.shapes import Cell, solver_cell
from rllock.orchestration.bench.specs import parse_list
from rllock.search.curriculum import NamedTask, parse_named_task
from rllock.search.guide import Guide, untrained_like
from rllock.search.search_config import SearchConfig

log = logging.getLogger(__name__)

ARMS = ("solver", "guided", "untrained")


def parse_cells(spec: str) -> list[NamedTask]:
    return parse_list(spec, [], parse_named_task, "--cells")


@dataclass(frozen=True)
class GuideRow:
    cell: NamedTask
    voxels: int
    arms: dict[str, list[Cell]]  # by arm, one per seed


def bench_guide(
    cells: list[NamedTask],
    guide: Guide,
    *,
    seeds: list[int],
    arms: list[str],
    time_limit: float,
    config: SearchConfig = SearchConfig(),
    untrained_seed: int = 0,
) -> list[GuideRow]:
    """Each cell's arms side by side per seed; `config` is every arm's search (its guide settings apply
    to the guided arms only); the untrained arm's initial weights are drawn with `untrained_seed`."""
    untrained = untrained_like(guide, untrained_seed)
    guides = {"solver": None, "guided": guide, "untrained": untrained}
    rows = []
    for cell in cells:
        task = cell.task()
        if cell.resolution is None:  # a mesh is voxelized once, by `task()`
            warm_process(cell.shape, cell.pieces)
        for g in (guide, untrained):  # the network compiled before any arm is timed (one batch shape)
            g.values(task, [initial_state(task)], [1.0])
        results: dict[str, list[Cell]] = {arm: [] for arm in arms}
        for seed in seeds:
            for arm in arms:
                results[arm].append(solver_cell(task, time_limit, seed, guides[arm], config=config))
                log.info("%s seed %d %s: %s", cell.label, seed, arm, results[arm][-1].text(task.pieces))
        rows.append(GuideRow(cell, task.size, results))
    return rows


def median_seconds(cells: list[Cell]) -> float:
    """The median of the seeds' seconds, an unsolved seed counted at the time limit."""
    return statistics.median(c.seconds if c.seconds is not None else c.limit for c in cells)


def arm_name(arm: str, untrained_seed: int) -> str:
    """An arm as the table names it: the untrained arm with the seed of its initial weights, since
    untrained networks of different seeds pick dive states very differently."""
    return f"untrained, seed {untrained_seed}" if arm == "untrained" else arm


def format_guide_table(
    rows: list[GuideRow], arms: list[str], guide: Guide, command: str, limit: float, untrained_seed: int = 0
) -> str:
    head = " | ".join(f"{arm_name(arm, untrained_seed)} (s per seed; median)" for arm in arms)
    lines = [
        f"Seconds to the first valid assembly, {limit:.0f} s limit, guide {guide.source} (`{command}`):",
        "",
        f"| cell | N | {head} | solver / guided |",
        "|---|---|" + "---|" * len(arms) + "---|",
    ]
    for row in rows:
        k = row.cell.pieces
        cells = [
            ", ".join(c.text(k) for c in row.arms[arm]) + f"; {median_seconds(row.arms[arm]):.1f}"
            for arm in arms
        ]
        ratio = "-"
        if "solver" in row.arms and "guided" in row.arms:
            ratio = f"{median_seconds(row.arms['solver']) / median_seconds(row.arms['guided']):.2f}"
        lines.append(f"| {row.cell.label} | {row.voxels} | " + " | ".join(cells) + f" | {ratio} |")
    return "\n".join(lines) + "\n"


def rows_json(rows: list[GuideRow]) -> list[dict]:
    return [
        {
            "cell": r.cell.label,
            "voxels": r.voxels,
            **{
                arm: [{"seconds": c.seconds, "placed": c.placed} for c in cells]
                for arm, cells in r.arms.items()
            },
        }
        for r in rows
    ]
