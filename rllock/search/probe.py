"""A bounded probe: tasks near one whose search failed (another K, the thin parts grown), or the piece counts
a shape suggests, each searched by the solver for a few seconds on the free cores, so that a failure can
offer a task that works and a suggestion is one.

The offer holds by construction: the solver is the same search with the same seed, which finds the same
assembly again in about the same time. Candidates are tried nearest first, as many at once as there are
workers; the probe stops after the first round that finds one, and offers the nearest that did."""

from __future__ import annotations

import math
import multiprocessing
import os
import signal
import time
from dataclasses import dataclass

import numpy as np

from rllock.errors import RLLockError


@dataclass(frozen=True)
class Candidate:
    """A task near the failed one: another K, and or the shape's thin parts grown to `thicken`."""

    pieces: int
    thicken: int | None = None


@dataclass(frozen=True)
class Outcome:
    candidate: Candidate
    seconds: float | None  # to the first assembly; None: none within the probe's time, or no assembly
    piece_size: int  # n of the task tried (the shape it was tried on, grown or not)
    last_size: int


SUGGEST_SECONDS = 10.0
"""A suggestion's time for each K it tries (at least): a K a minute's search finds in seconds."""
NEARBY_SECONDS = 6.0
"""A failure's time for each task near it: the nearest that work were found in 1-5 s, and shorter tries
let a probe reach the tasks a little further off (a figure's thin parts grown)."""


def default_probe_seconds(time_limit: float) -> float:
    """A failed search's probe: half its time limit, from 10 s (a nearby task found in a few seconds
    is worth the wait after a short search) to 30 s."""
    return min(30.0, max(10.0, time_limit / 2))


SUGGESTED_SIZES = (20, 25, 30, 40, 60, 80, 120)
"""Piece sizes a suggestion tries, in order of preference: pieces of about 20 voxels make a puzzle of
many pieces that the search finds quickly on most shapes; larger ones where it does not (thin figures,
shapes of many thousand voxels)."""


SUGGESTED_MAX_PIECES = 200
"""A suggestion's most pieces: the search's time grows with K, and a few hundred pieces take it more than
a probe's seconds (a scan of 18,198 voxels: K = 910 took a minute); larger shapes get larger pieces."""


def suggestions(size: int) -> list[Candidate]:
    """The K of each of SUGGESTED_SIZES for a shape of `size` voxels (K = N / n rounded: a last piece
    a little over the others, easier than the smallest), at most SUGGESTED_MAX_PIECES, in order; K from 2
    up."""
    ks = [min(max(2, round(size / n)), SUGGESTED_MAX_PIECES) for n in SUGGESTED_SIZES]
    return [Candidate(k) for k in dict.fromkeys(ks) if k <= size]


def nearby(pieces: int, size: int, thicken: int | None = None) -> list[Candidate]:
    """Tasks near K = `pieces` on `size` voxels, nearest first: one or two pieces more or fewer (one more
    often leaves a last piece well over the others, which is easier), then larger pieces (a tenth, a
    fifth, a third and half fewer pieces), and with `thicken`, the same K on the shape with its thin
    parts grown."""
    ks = [pieces + 1, pieces - 1, pieces + 2, pieces - 2]
    ks += [round(pieces * f) for f in (0.9, 0.8, 2 / 3, 0.5)]
    found = [Candidate(k) for k in dict.fromkeys(ks) if 2 <= k <= size and k != pieces]
    if thicken is not None:  # it changes the shape, not the count: after the K one off
        found.insert(min(2, len(found)), Candidate(pieces, thicken))
    return found


def suggest(
    grid: np.ndarray, removal: str, *, seed: int, budget: float, workers: int | None = None
) -> Outcome | None:
    """The first of `suggestions` for `grid` that the solver with `seed` finds an assembly for: the K a
    shape is given when it names none (`probe` for `budget` seconds, SUGGEST_SECONDS a K at least)."""
    candidates = suggestions(int(np.asarray(grid).sum()))
    seconds = min(SUGGEST_SECONDS, budget)
    return probe(grid, removal, candidates, seed=seed, seconds=seconds, budget=budget, workers=workers)


def nearest_that_works(
    grid: np.ndarray,
    removal: str,
    pieces: int,
    *,
    grown: bool,
    seed: int,
    budget: float,
    workers: int | None = None,
) -> Outcome | None:
    """The nearest task to K = `pieces` on `grid` (`nearby`) that the solver with `seed` finds an
    assembly for: another K, or, when the shape has thin parts worth growing and was not `grown`
    already, the same K on it grown (`probe` for `budget` seconds, NEARBY_SECONDS a task at least)."""
    from rllock.core.thickness import THIN_WIDTH, thin_enough_to_matter

    size = int(np.asarray(grid).sum())
    thin = not grown and thin_enough_to_matter(grid, size // pieces) is not None
    candidates = nearby(pieces, size, THIN_WIDTH if thin else None)
    seconds = min(NEARBY_SECONDS, budget)
    return probe(grid, removal, candidates, seed=seed, seconds=seconds, budget=budget, workers=workers)


def probe(
    grid: np.ndarray,
    removal: str,
    candidates: list[Candidate],
    *,
    seed: int,
    seconds: float,
    budget: float,
    workers: int | None = None,
) -> Outcome | None:
    """The nearest of `candidates` (in their order) that the solver with `seed` finds an assembly for
    within `seconds` (more where the budget leaves more to each), trying `workers` at once (default: the
    cores this process may use; one: in this process) for at most `budget` seconds in all; None when
    none of those tried did."""
    workers = workers or usable_cores()
    seconds = max(seconds, min(budget, budget / math.ceil(max(len(candidates), 1) / workers)))
    rounds = max(1, int(budget // max(seconds, 1e-3)))
    todo = candidates[: rounds * workers]
    if not todo:
        return None
    if workers == 1:  # one at a time here: no process to start (a service's job has one core)
        tried = (_try((grid, removal, c, seed, seconds)) for c in todo)
        return next((o for o in tried if o.seconds is not None), None)
    # Ctrl-C is the caller's to handle: workers that took it would end their searches early, which
    # reads as no assembly found.
    pool = multiprocessing.get_context("spawn").Pool(min(workers, len(todo)), _ignore_sigint)
    try:
        for start in range(0, len(todo), workers):
            pending = [
                pool.apply_async(_try, ((grid, removal, c, seed, seconds),))
                for c in todo[start : start + workers]
            ]
            found = _nearest_found(pending)
            if found is not None:
                return found
    finally:
        pool.terminate()  # the other candidates' searches, still running, are not needed
        pool.join()
    return None


def _ignore_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def usable_cores() -> int:
    """The cores this process may run on (its affinity where the system has one)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def _nearest_found(pending: list) -> Outcome | None:
    """The first of `pending` (in order) that found an assembly, as soon as every one before it is known
    to have found none; None when none did."""
    for result in pending:
        outcome = result.get()
        if outcome.seconds is not None:
            return outcome
    return None


def _try(args: tuple[np.ndarray, str, Candidate, int, float]) -> Outcome:
    """One candidate searched for `seconds` (in a worker process)."""
    from rllock.core.env import make_task
    from rllock.core.feasibility import impossibility
    from rllock.core.thickness import thicken
    from rllock.search.solver import search

    grid, removal, candidate, seed, seconds = args
    shape = grid if candidate.thicken is None else thicken(grid, candidate.thicken)
    try:
        task = make_task(shape, candidate.pieces, removal)
    except RLLockError:
        return Outcome(candidate, None, 0, 0)
    if impossibility(task) is not None:
        return Outcome(candidate, None, task.piece_size, task.last_size)
    start = time.monotonic()
    found = next(search(task, seed=seed, time_limit=seconds), None)
    elapsed = None if found is None else time.monotonic() - start
    return Outcome(candidate, elapsed, task.piece_size, task.last_size)
