"""What `solve` says when its search found nothing: how far it got and why its next piece failed, the
shape's thin parts, and a task near it that works, found by a bounded probe (`rllock.search.probe`); and
the K it suggests, by the same probe, when it is given none."""

from __future__ import annotations

import argparse
import logging
import math
import shlex

from rllock.core.env import Task, rejections
from rllock.errors import RLLockError
from rllock.orchestration.cli.longwork import advice, general_serves
from rllock.search.probe import (
    NEARBY_SECONDS,
    SUGGEST_SECONDS,
    SUGGESTED_SIZES,
    Candidate,
    default_probe_seconds,
    nearest_that_works,
    suggest,
)

log = logging.getLogger(__name__)


def probe_budget(args: argparse.Namespace) -> float:
    """--probe's seconds (`default_probe_seconds` unless given)."""
    return default_probe_seconds(args.time_limit) if args.probe is None else max(args.probe, 0.0)


def suggested_pieces(grid, args: argparse.Namespace) -> int | None:
    """A K for `grid` when --pieces is not given: the first of `rllock.search.probe.SUGGESTED_SIZES`
    (pieces of about 20 voxels, then larger) that this search (--seed) finds an assembly for within the
    probe's seconds, tried on the free cores for --probe's seconds; None when none did."""
    budget = probe_budget(args)
    if budget <= 0:
        raise RLLockError("give --pieces: without it solve tries piece counts, which --probe 0 turns off")
    log.info(
        "no --pieces: trying pieces of %s voxels, %g s each, for up to %.0f s",
        ", ".join(map(str, SUGGESTED_SIZES)),
        min(SUGGEST_SECONDS, budget),
        budget,
    )
    found = suggest(grid, args.removal, seed=args.seed, budget=budget)
    if found is not None:
        log.info(
            "K=%d: pieces of %d, the last %d; this search found one in %.1f s",
            found.candidate.pieces,
            found.piece_size,
            found.last_size,
            found.seconds,
        )
        return found.candidate.pieces
    return None


def thin_parts(task: Task, args: argparse.Namespace) -> str | None:
    """Why a figure's search may end short: how much of the shape is thin, and how to grow it (None when
    little of it is, or when --thicken already grew it)."""
    from rllock.core.thickness import THIN_WIDTH, thicken, thin_enough_to_matter

    grid = task.topology.grid
    thin = None if args.thicken is not None else thin_enough_to_matter(grid, task.piece_size)
    if thin is None:
        return None
    grown = int(thicken(grid, THIN_WIDTH).sum())
    return (
        f"  thin parts: {thin:,} of the {task.size:,} voxels lie where the shape is at most "
        f"{THIN_WIDTH - 1} voxels thick (arms, legs, ears, tails), where pieces have little room to hold "
        f"or be held: larger pieces help (a smaller K, or --thicken {THIN_WIDTH}, which grows the thin "
        f"parts to {grown:,} voxels in all, pieces of {grown // task.pieces} at this K), and so does a "
        "higher --resolution"
    )


def nothing_found(task: Task, args: argparse.Namespace, stats) -> str:
    """What a search that found nothing reached and why its deepest state's next piece failed."""
    lines = [
        f"solve: no valid assembly of {task.shape_name} K={task.pieces} within {args.time_limit:g} s "
        f"({stats.expansions:,} node expansions, {stats.restarts} restarts)",
        f"  best: {stats.placed} of {task.pieces - 1} pieces placed",
    ]
    if stats.deepest is not None:
        raw, failed = rejections(task, stats.deepest, seed=args.seed, num_samples=512)
        piece = stats.placed + 1
        if raw == 0:
            lines[-1] += f"; piece {piece} cannot grow to n = {task.piece_size} voxels there"
        else:
            order = sorted(failed, key=lambda name: -failed[name])
            lines[-1] += f"; of {raw} chunks sampled for piece {piece}, " + ", ".join(
                f"{failed[name]} fail {name}" for name in order
            )
    thin = thin_parts(task, args)
    if thin is not None:
        lines.append(thin)
    return "\n".join(lines) + "\n"


def offer(task: Task, args: argparse.Namespace) -> str:
    """The nearest task that works, found by a probe of --probe seconds with the same seed, as a command
    to run; else what to try."""
    budget = probe_budget(args)
    more = f"more time (--time-limit {2 * args.time_limit:g})"
    fallback = "  " + advice(task, fits_general=general_serves(task), more=more) + "\n"
    if budget <= 0:
        return fallback
    log.info("looking for a task near it that works, for up to %.0f s (--probe 0 skips this)", budget)
    try:
        found = nearest_that_works(
            task.topology.grid,
            task.removal,
            task.pieces,
            grown=args.thicken is not None,
            seed=args.seed,
            budget=budget,
        )
    except KeyboardInterrupt:
        return fallback
    if found is None:
        seconds = min(NEARBY_SECONDS, budget)
        return f"  no task near it found an assembly within {seconds:g} s either;\n" + fallback
    c = found.candidate
    grown = "" if c.thicken is None else f" on the shape with its thin parts grown (--thicken {c.thicken})"
    return (
        f"  a task that works: K={c.pieces}{grown}, pieces of {found.piece_size} and the last "
        f"{found.last_size}; this search (seed {args.seed}) found one in {found.seconds:.1f} s:\n"
        f"    {retry_command(args, c, enough_time(round(found.seconds or 0.0, 1)))}\n"
    )


def enough_time(seconds: float) -> float:
    """A time limit that lets the same search find again what it found in `seconds` (as shown, to a tenth),
    on a busier machine."""
    return float(math.ceil(3 * seconds) + 5)


def retry_command(args: argparse.Namespace, candidate: Candidate, time_limit: float) -> str:
    """The `rllock solve` command of `args` with the candidate's K and thickening, and `time_limit` when
    the one of `args` is less."""
    words = ["rllock", "solve", "--shape", args.shape]
    if args.resolution is not None:
        words += ["--resolution", str(args.resolution)]
    words += ["--pieces", str(candidate.pieces)]
    if args.removal != "straight":
        words += ["--removal", args.removal]
    thicken = candidate.thicken if candidate.thicken is not None else args.thicken
    if thicken is not None:
        words += ["--thicken", str(thicken)]
    if args.time_limit < time_limit:
        words += ["--time-limit", f"{time_limit:g}"]
    words += ["--seed", str(args.seed), "--out", str(args.out)]
    return shlex.join(words)
