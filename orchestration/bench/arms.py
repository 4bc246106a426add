"""What the table benches share (paper, transfer, shapes, ablation): an arm of a row, run under the
paper's protocol and timed with what it loads and compiles, and its JSON and table cells.

Each network arm says how it started (`Arm.cache`): cold when it compiled programs that JAX's persistent
cache (`rllock.process.setup_jax_cache`) did not hold yet, and so wrote them there; warm when it wrote
none; off without the cache. The tree search itself calls back to the host, which JAX never caches, so
an MCTS arm compiles it either way.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypedDict

import jax

from rllock.core.env import Task, initial_state, make_task, sample_accepted
from rllock.process import jax_cache_entries
from rllock.search.inference import Policy, generate
from rllock.search.solver import search

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Arm:
    valid: int
    episodes: int | None  # None for the search solver
    seconds: float
    cache: str | None = None  # network arms: "cold", "warm" or "off" (see the module's docstring)

    @property
    def time_per_valid_s(self) -> float | None:
        return self.seconds / self.valid if self.valid else None


def warm_process(shape: str, pieces: int) -> None:
    """Pay the once-per-process costs before any arm is timed: the sampler's compiled code (numba's
    cache) and JAX's backend."""
    t = make_task(shape, pieces)
    sample_accepted(t, initial_state(t), seed=0, num_samples=1)
    jax.block_until_ready(jax.numpy.zeros(1) + 1)


class ArmProtocol(TypedDict):
    """The protocol every network arm of a row runs: `policy_arm`'s keyword arguments."""

    count: int
    batch: int
    time_limit: float
    seed: int


def policy_arm(
    load: Callable[[], Policy], *, count: int, batch: int, time_limit: float, seed: int
) -> tuple[Arm, Policy]:
    """The protocol with the policy `load` gives, its loading and its search's compiling timed with it."""
    before = jax_cache_entries()
    t0 = time.perf_counter()
    policy = load()
    r = generate(policy, count=count, batch=batch, time_limit=time_limit, seed=seed, progress=False)
    seconds = time.perf_counter() - t0
    after = jax_cache_entries()
    arm = Arm(r.valid, r.episodes, seconds, cache_start(before, after))
    log.info(
        "%s: %d valid in %.1f s (%s start: %s)",
        policy.source,
        arm.valid,
        arm.seconds,
        arm.cache,
        "no persistent cache" if after is None else f"{after - (before or 0)} programs added to the cache",
    )
    return arm, policy


def cache_start(before: int | None, after: int | None) -> str:
    """How an arm started, from the programs JAX's persistent cache held before and after it: cold when
    it added any, warm when it added none, off without the cache."""
    if before is None or after is None:
        return "off"
    return "cold" if after > before else "warm"


def solver_arm(task: Task, *, count: int, time_limit: float, seed: int) -> Arm:
    """The search solver until `count` assemblies or the limit."""
    t0 = time.perf_counter()
    found = 0
    for _ in search(task, seed=seed, time_limit=time_limit):
        found += 1
        if found >= count:
            break
    arm = Arm(found, None, time.perf_counter() - t0)
    log.info("solver: %d valid in %.1f s", arm.valid, arm.seconds)
    return arm


def arm_json(a: Arm | None) -> dict | None:
    if a is None:
        return None
    return {
        "valid": a.valid,
        "episodes": a.episodes,
        "seconds": round(a.seconds, 2),
        "time_per_valid_s": a.time_per_valid_s,
        "cache": a.cache,
    }


def arm_cell(a: Arm | None) -> str:
    """An arm in a markdown table: seconds per valid assembly (valid found), or none in S seconds."""
    if a is None:
        return "not shipped"
    if not a.valid:
        return f"none in {a.seconds:.0f}"
    return f"{a.time_per_valid_s:.1f} ({a.valid})"


def protocol_note(count: int, batch: int, time_limit: float) -> str:
    """What a table's protocol was, for its caption."""
    return f"{count} wanted, batches of {batch}, {time_limit:.0f} s limit per arm"
