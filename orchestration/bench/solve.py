"""Benchmark commands: `rllock bench checkers` and `rllock bench solve`."""

from __future__ import annotations

import logging
import statistics
import time
from dataclasses import dataclass

from rllock.core.env import State, Task, initial_state, make_task, sample_accepted
from rllock.errors import RLLockError
from rllock.orchestration.bench.specs import parse_list
from rllock.search.restarts import reach_depth
from rllock.search.search_config import SearchConfig
from rllock.search.solver import search

log = logging.getLogger(__name__)

# The paper's inference times (minutes, RTX 5090 workstation; None = nothing valid within 60 minutes),
# Table 1 of the RL-Lock paper (AAAI 2027 preprint): (cube size, K) -> (RL-Lock infer, DESIA).
PAPER_MINUTES: dict[tuple[int, int], tuple[float, float | None]] = {
    (4, 7): (0.05, 0.01),
    (4, 8): (0.47, 0.50),
    (4, 9): (1.22, None),
    (5, 13): (0.60, 0.01),
    (5, 14): (0.84, 0.86),
    (5, 16): (1.68, 21.36),
    (6, 20): (2.86, 0.12),
    (6, 22): (3.46, 2.54),
    (6, 25): (4.87, 32.26),
}


@dataclass(frozen=True)
class CheckerBench:
    chunks_per_sec: float  # median over the timed repeats
    accept_rate: float
    states: int
    repeats: int


def mid_episode_states(task: Task, placed: int, count: int, seed: int) -> list[State]:
    """`count` valid states with `placed` pieces, reached by the search with seeds seed, seed+1, ..."""
    states: list[State] = []
    s = seed
    while len(states) < count:
        state = reach_depth(task, placed, seed=s, time_limit=60.0)
        if state is None:
            raise RLLockError(f"could not reach piece {placed + 1} of {task.shape_name} K={task.pieces}")
        states.append(state)
        s += 1
    return states


def bench_checkers(
    *,
    shape: str = "cube6",
    pieces: int = 25,
    piece: int = 13,
    seconds: float = 5.0,
    samples: int = 1024,
    seed: int = 0,
    removal: str = "straight",
) -> CheckerBench:
    """Raw chunks sampled and checked per second on one core: calls of `samples` chunks (one search
    node's worth, including its per-node preparation) cycling over seeded mid-episode states."""
    task = make_task(shape, pieces, removal)
    if not 1 <= piece <= pieces - 1:
        raise RLLockError(f"--piece must be between 1 and K-1 = {pieces - 1}, got {piece}")
    states = mid_episode_states(task, piece - 1, 8, seed)
    sample_accepted(task, states[0], seed=0, num_samples=16)  # compile before timing
    rates: list[float] = []
    accepted = total = 0
    deadline = time.perf_counter() + seconds
    call = 0
    while time.perf_counter() < deadline or len(rates) < 5:
        state = states[call % len(states)]
        t0 = time.perf_counter()
        got = sample_accepted(task, state, seed=seed + call, num_samples=samples)
        rates.append(samples / (time.perf_counter() - t0))
        accepted += len(got)
        total += samples
        call += 1
    return CheckerBench(statistics.median(rates), accepted / total, len(states), len(rates))


def parse_tasks(spec: str | None) -> list[tuple[int, int]]:
    """'5^3:13,6^3:20' -> [(5, 13), (6, 20)]; None -> the nine paper tasks."""
    return parse_list(spec, list(PAPER_MINUTES), _paper_cube, "--tasks")


def _paper_cube(item: str) -> tuple[int, int]:
    try:
        cube_part, k_part = item.split(":")
        task = (int(cube_part.removesuffix("^3")), int(k_part))
    except ValueError:
        raise RLLockError(f"bad task {item!r}: write tasks like 5^3:13,6^3:20") from None
    if task not in PAPER_MINUTES:
        known = ", ".join(f"{s}^3:{k}" for s, k in PAPER_MINUTES)
        raise RLLockError(f"unknown task {item!r}: the paper's tasks are {known}")
    return task


@dataclass(frozen=True)
class SolveRow:
    task: str
    found: int
    seconds: float
    time_per_valid_s: float | None  # None when nothing was found
    paper_rllock_s: float
    paper_desia_s: float | None
    ratio: float | None  # ours / paper RL-Lock


def bench_solve_task(
    size: int, pieces: int, *, count: int, time_limit: float, seed: int, config: SearchConfig
) -> SolveRow:
    task = make_task(f"cube{size}", pieces)
    sample_accepted(task, initial_state(task), seed=0, num_samples=1)  # load compiled code before timing
    t0 = time.perf_counter()
    found = 0
    for _ in search(task, seed=seed, time_limit=time_limit, config=config):
        found += 1
        if found >= count:
            break
    elapsed = time.perf_counter() - t0
    rl_min, desia_min = PAPER_MINUTES[(size, pieces)]
    per_valid = elapsed / found if found else None
    return SolveRow(
        f"{size}^3 K={pieces}",
        found,
        elapsed,
        per_valid,
        rl_min * 60,
        None if desia_min is None else desia_min * 60,
        None if per_valid is None else per_valid / (rl_min * 60),
    )


def format_solve_table(rows: list[SolveRow], time_limit: float) -> str:
    def secs(v: float | None, limit: bool = False) -> str:
        if v is None:
            return f"> {time_limit:.0f}" if limit else "-"
        return f"{v:.2f}"

    lines = [
        "| task | found | time per valid (s) | paper RL-Lock (s) | ratio | paper DESIA (s) |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        ratio = "-" if r.ratio is None else f"{r.ratio:.3f}"
        lines.append(
            f"| {r.task} | {r.found} | {secs(r.time_per_valid_s, True)} | {r.paper_rllock_s:.1f} | "
            f"{ratio} | {secs(r.paper_desia_s)} |"
        )
    beat = sum(1 for r in rows if r.ratio is not None and r.ratio <= 0.1)
    lines.append(f"\nAt most 1/10 of the paper's RL-Lock time on {beat} of {len(rows)} tasks.")
    return "\n".join(lines)
