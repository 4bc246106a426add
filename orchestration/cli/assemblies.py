"""The assembly commands: `verify` and `solve` (no training needed), `show` (pictures) and `export`
(files to make an assembly from).

`add_commands(subparsers)` adds them to the `rllock` parser; each handler takes the parsed arguments,
raises RLLockError on bad input and returns the exit status.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from rllock.core.reference_checkers import REMOVAL_MODES
from rllock.core.verifier import Verdict, verify_labels
from rllock.errors import RLLockError
from rllock.files.assembly import read_assembly, write_assembly
from rllock.files.export import FORMATS, MESH_FORMATS, PRINT_GAP, write_meshes, write_xmpuzzle
from rllock.orchestration.cli.common import (
    add_protocol_args,
    add_task_args,
    assemblies_word,
    fresh_out,
    picture_writer,
)
from rllock.orchestration.cli.failure import nothing_found, offer, suggested_pieces
from rllock.orchestration.cli.longwork import (
    INTERRUPTED,
    graceful_stop,
    is_interrupt,
    kept,
)
from rllock.search.probe import SUGGESTED_SIZES

log = logging.getLogger(__name__)
PROGRESS_LOG_EVERY = 5.0  # seconds between progress lines in a log (stderr not a terminal)


def verified(labels: np.ndarray, metadata: dict, source: str) -> Verdict:
    """The verdict with the removal mode the assembly was made for: the one its assembly.json names, or
    for a bare .puz the first of "straight" and "path" under which it is valid."""
    modes = [metadata["removal"]] if metadata.get("removal") else list(REMOVAL_MODES)
    for mode in modes:
        verdict = verify_labels(labels, mode)
        if verdict.valid:
            return verdict
    raise RLLockError(
        f"{source} is not a valid assembly (removal={' or '.join(modes)}): "
        f"stage {verdict.failed_stage} fails the {verdict.failed_check} check"
    )


def cmd_verify(args: argparse.Namespace) -> int:
    from rllock.core.verifier import verify_labels

    try:
        labels, meta = read_assembly(args.file)
        verdict = verify_labels(labels, args.removal or meta.get("removal") or "straight")
    except (RLLockError, OSError) as exc:
        if not args.json:
            raise
        # A script reading --json output gets an answer on stdout for bad input too; stderr keeps the line.
        error = str(exc) if isinstance(exc, RLLockError) else f"{exc.strerror or exc}: {exc.filename or ''}"
        sys.stdout.write(json.dumps({"file": str(args.file), "valid": None, "error": error}) + "\n")
        sys.stderr.write(f"rllock: error: {error}\n")
        return 2
    if args.json:
        sys.stdout.write(json.dumps({"file": str(args.file), **verdict.to_json()}) + "\n")
    elif verdict.valid:
        sys.stdout.write(f"valid: {verdict.pieces} pieces, removal={verdict.removal}, key = piece 1\n")
    else:
        sys.stdout.write(
            f"invalid: stage {verdict.failed_stage} fails the {verdict.failed_check} check "
            f"(removal={verdict.removal})\n"
        )
    return 0 if verdict.valid else 1


def cmd_solve(args: argparse.Namespace) -> int:
    from rllock.core.env import make_task, tight
    from rllock.core.feasibility import check_feasible
    from rllock.search.dfs import SearchStats

    if args.workers < 1:
        raise RLLockError(f"--workers must be at least 1, got {args.workers}")
    if args.threads < 1:
        raise RLLockError(f"--threads must be at least 1, got {args.threads}")
    if args.threads > 1 and args.address is not None:
        raise RLLockError("--threads is for a search on this machine; with --address each worker has one CPU")
    if args.threads > 1 and args.workers > 1:
        raise RLLockError(
            "--threads is for one search; --workers N shares its N cores between seeds and threads"
        )
    grid = _shape(args)
    pieces = args.pieces if args.pieces is not None else suggested_pieces(grid, args)
    if pieces is None:
        sys.stdout.write(
            f"solve: no piece count for {args.shape} with pieces of {SUGGESTED_SIZES[0]} to "
            f"{SUGGESTED_SIZES[-1]} voxels gave an assembly within the probe's time; give --pieces "
            "(and more --time-limit), or --thicken 3 for a figure's thin parts\n"
        )
        return 1
    task = make_task(grid, pieces, args.removal, name=args.shape)
    check_feasible(task)
    if not tight(task.size, task.pieces):
        n = task.piece_size
        smallest = replace(task, pieces=task.size // n)
        log.info(
            "K=%d on %d voxels: pieces of %d and a last piece of %d, which makes the task easier; "
            "K=%d gives pieces of %d and the smallest last piece (%d)",
            task.pieces,
            task.size,
            n,
            task.last_size,
            smallest.pieces,
            n,
            smallest.last_size,
        )
    guide = None
    if args.guide is not None:
        from rllock.search.dives import dive_depth
        from rllock.search.guide_checkpoint import load_guide

        guide = load_guide(args.guide)  # a bad checkpoint is an error before any search
        if dive_depth(task, guide) < 1:
            log.info(
                "--guide: K=%d leaves no state %d pieces before the end to dive to, so the search is "
                "the solver's",
                task.pieces,
                guide.horizon,
            )
    joined = args.address is not None and _join_ray(args.address)
    out = fresh_out(args.out)
    written: list[Path] = []
    stats = SearchStats()
    start = time.perf_counter()
    try:
        with graceful_stop() as stop:
            _solve_into(task, args, out, written, stats, stop, guide)
            stopped = stop()
    except (KeyboardInterrupt, SystemError) as exc:
        if not is_interrupt(exc):
            raise
        stopped = True
    finally:
        if joined:
            import ray

            ray.shutdown()
    if stopped:
        sys.stdout.write(kept("solve", len(written), out))
        return INTERRUPTED
    if not written:
        sys.stdout.write(nothing_found(task, args, stats))
        sys.stdout.flush()
        sys.stdout.write(offer(task, args))
        return 1
    elapsed = time.perf_counter() - start
    sys.stdout.write(
        f"solve: {len(written)} valid {assemblies_word(len(written))} of {task.shape_name} "
        f"K={task.pieces} in {elapsed:.2f} s: {elapsed / len(written):.3f} s per valid assembly -> {out}\n"
    )
    return 0


def _join_ray(address: str) -> bool:
    """Join the Ray cluster at `address` for the search workers; a cluster that cannot be reached is one
    line. True when this process connected (and so disconnects at the end)."""
    from rllock.orchestration.pool import start_ray

    try:
        return start_ray(address)
    except (ConnectionError, RuntimeError, ValueError) as exc:  # reachable, but not a Ray cluster's head
        raise RLLockError(f"cannot join the Ray cluster at {address}: {str(exc).splitlines()[0]}") from None


def _solve_into(task, args: argparse.Namespace, out: Path, written: list[Path], stats, stop, guide) -> None:
    """Search until --count assemblies, --time-limit or `stop()`, writing each (verified) as it comes and
    adding its folder to `written`; the bar shows the search's progress. `guide`: a guide network or
    None (the plain search)."""
    from rllock.search.portfolio import portfolio_search
    from rllock.search.search_config import SearchConfig
    from rllock.search.solver import search

    config = SearchConfig()
    picture = picture_writer()
    desc = f"solve {task.shape_name} K={task.pieces}"
    began = time.monotonic()
    logged = [began]  # when the last progress line was logged
    with tqdm(total=args.count, desc=desc, unit="assembly", disable=None) as bar:

        def report(s) -> None:
            bar.set_postfix_str(progress(s, task.pieces))
            now = time.monotonic()
            # No terminal, no bar (tqdm disables itself): a log line every few seconds instead, so that a
            # long search in a log file is told apart from a hang.
            if bar.disable and now - logged[0] >= PROGRESS_LOG_EVERY:
                logged[0] = now
                elapsed = now - began
                log.info(
                    "%s: %s, %.0f nodes/s, %.0f s",
                    desc,
                    progress(s, task.pieces),
                    s.expansions / elapsed,
                    elapsed,
                )

        common = dict(
            time_limit=args.time_limit, config=config, stats=stats, stop=stop, report=report, guide=guide
        )
        on_ray = args.address is not None
        if args.workers == 1 and not on_ray:
            found = search(task, seed=args.seed, threads=args.threads, **common)
        else:
            found = portfolio_search(task, seed=args.seed, workers=args.workers, on_ray=on_ray, **common)
        for f in found:
            folder = out / f"assembly_{len(written) + 1:03d}"
            write_assembly(
                folder,
                f.labels,
                removal=task.removal,
                # The voxels are the grown shape's: the name says so.
                shape=task.shape_name + ("" if args.thicken is None else f" (--thicken {args.thicken})"),
                method={
                    "name": "search",
                    **asdict(config),
                    **({} if guide is None else {"guide": guide.source}),
                    **({} if args.workers == 1 and not on_ray else {"workers": args.workers}),
                    **({"ray": True} if on_ray else {}),
                },
                seed=f.seed,
                timings={"seconds": round(f.seconds, 4), "node_expansions": f.expansions},
                picture=picture,
            )
            written.append(folder)
            log.info("wrote %s (%.2f s)", folder, f.seconds)
            bar.update(1)
            if len(written) >= args.count:
                break


def progress(stats, pieces: int) -> str:
    """A search's progress in words: nodes, restarts and the most pieces placed."""
    return (
        f"{stats.expansions:,} nodes, {stats.restarts} restarts, best {stats.placed} of {pieces - 1} placed"
    )


def _shape(args: argparse.Namespace) -> np.ndarray:
    """The shape `solve` searches: --shape at --resolution, its thin parts grown when --thicken says so."""
    from rllock.core.shapes import load_shape, validate_shape
    from rllock.core.thickness import thicken

    if args.thicken is not None and args.thicken < 2:  # before the shape is read: a mesh takes seconds
        raise RLLockError(f"--thicken takes a width of at least 2 voxels, got {args.thicken}")
    grid = load_shape(args.shape, args.resolution)
    if args.thicken is None:
        return grid
    grown = validate_shape(thicken(grid, args.thicken), args.shape)
    log.info(
        "--thicken %d: %s has %d voxels, %d of them added to its thin parts",
        args.thicken,
        args.shape,
        int(grown.sum()),
        int(grown.sum() - grid.sum()),
    )
    return grown


def _name(source: str) -> str:
    path = Path(source)
    return "assembly" if path.is_dir() else path.stem


def cmd_show(args: argparse.Namespace) -> int:
    from rllock.files import render  # imported here: matplotlib is slow to import

    if not (args.png or args.gif or args.html):
        raise RLLockError("nothing to show: give --png, --gif and/or --html")
    labels, metadata = read_assembly(args.assembly)
    k = int(labels.max())
    if (args.gif or args.html) and k > render.MAX_ANIMATED:
        raise RLLockError(
            f"--gif and --html animate at most {render.MAX_ANIMATED} pieces and this assembly has {k}: "
            "use --png, or rllock export for the pieces"
        )
    if args.png:
        render.draw_png(labels, args.png, metadata.get("removal"))
        log.info("wrote %s", args.png)
    if args.gif or args.html:
        verdict = verified(labels, metadata, args.assembly)
        if args.gif:
            render.write_gif(labels, verdict, args.gif)
            log.info("wrote %s", args.gif)
        if args.html:
            render.write_html(labels, verdict, args.html)
            log.info("wrote %s", args.html)
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    labels, metadata = read_assembly(args.assembly)
    if args.format in MESH_FORMATS:
        if 0 < args.voxel_size <= args.gap:
            # The gap has a default, so a user who only made voxels small must learn which flag to change.
            raise RLLockError(
                f"--gap {args.gap:g} mm must be smaller than --voxel-size {args.voxel_size:g} "
                "mm: give a smaller --gap (0 for none)"
            )
        paths = write_meshes(labels, args.format, args.out, args.voxel_size, args.gap)
        log.info("wrote %d %s meshes to %s", len(paths), args.format.upper(), args.out)
    else:
        name = _name(args.assembly)
        path = write_xmpuzzle(
            labels, verified(labels, metadata, args.assembly), Path(args.out) / f"{name}.xmpuzzle", title=name
        )
        log.info("wrote %s", path)
    return 0


def _millimetres(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of millimetres, got {text!r}") from None
    if not np.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text}")
    return value


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    _add_checks(subparsers)
    _add_outputs(subparsers)


def _add_checks(subparsers: argparse._SubParsersAction) -> None:
    """verify and solve: an assembly checked, or found without training."""
    p = subparsers.add_parser("verify", help="check every stage of an assembly (.puz or assembly.json)")
    p.add_argument("file")
    p.add_argument(
        "--removal",
        choices=REMOVAL_MODES,
        default=None,
        help="default: the mode an assembly.json names, else straight",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=cmd_verify)

    p = subparsers.add_parser("solve", help="find assemblies by randomized search (no training needed)")
    add_task_args(p, pieces_help="default: a K the search finds an assembly for quickly, tried first")
    add_protocol_args(p, count=1, time_limit=60.0, batch=False, seed=False)
    p.add_argument("--out", required=True, help="folder; each assembly goes to OUT/assembly_NNN/")
    p.add_argument(
        "--guide",
        nargs="?",
        const="guide",
        default=None,
        metavar="CHECKPOINT",
        help="a guide network picks where the search's restarts begin: alone, the shipped one; or a run of "
        "rllock train-guide, or one of its checkpoints (default: the plain search)",
    )
    p.add_argument(
        "--workers",
        type=int,
        default=1,
        help="searches run at once from different seeds, on N cores: where nodes are costly the first "
        "samples on the others' cores while they wait; the first assemblies found are kept (default "
        "%(default)s: the plain search, reproducible by --seed)",
    )
    p.add_argument(
        "--threads",
        type=int,
        default=1,
        help="threads that sample a node's children in the search of --seed: the same search, node for "
        "node, sooner where nodes are costly (default %(default)s; one worker on this machine)",
    )
    p.add_argument(
        "--address",
        default=None,
        help="run the --workers searches as Ray actors (one CPU each) on the Ray cluster at this address "
        "(host:port of its head, or auto) instead of on this machine",
    )
    p.add_argument(
        "--thicken",
        type=int,
        default=None,
        metavar="W",
        help="grow the shape's thin parts (arms, legs, ears: where no W^3 block fits) by a voxel all "
        "round until one does; the rest of the shape is kept (try 3 when a figure's limbs stop the search)",
    )
    p.add_argument(
        "--probe",
        type=float,
        default=None,
        metavar="SECONDS",
        help="the seconds of short searches on the free cores: without --pieces, of the K to take; when "
        "the search finds nothing, of tasks near it (another K, thin parts grown), to offer the nearest "
        "that works (default: half of --time-limit, from 10 to 30; 0: none)",
    )
    p.set_defaults(func=cmd_solve)


def _add_outputs(subparsers: argparse._SubParsersAction) -> None:
    """show and export: pictures of an assembly, and files to make it from."""
    p = subparsers.add_parser(
        "show",
        help="draw an assembly: PNG picture, GIF animation, interactive HTML page",
        description="Draw an assembly (assembly.json, its folder, or a .puz file). The GIF and HTML follow "
        "the verified disassembly, recomputed with the removal mode in assembly.json "
        "(a .puz is tried with straight, then path).",
    )
    p.add_argument("assembly", help="assembly.json, a folder holding one, or a .puz file")
    p.add_argument("--png", metavar="FILE", help="assembled and exploded views")
    p.add_argument("--gif", metavar="FILE", help="the disassembly animated")
    p.add_argument("--html", metavar="FILE", help="self-contained interactive 3D page")
    p.set_defaults(func=cmd_show)

    p = subparsers.add_parser(
        "export",
        help="write the pieces as OBJ/STL meshes or a BurrTools .xmpuzzle",
        description="obj/stl: one watertight mesh per piece (OUT/piece_NN.stl), in millimetres, in its "
        "assembled position; --gap shrinks each piece by GAP/2 on every face that touches "
        "another piece or the outside, so neighbouring pieces have GAP between them (default "
        f"{PRINT_GAP:g} mm, a printing clearance that also keeps STL files watertight when "
        "voxels of a piece touch only along an edge; --gap 0 gives the exact shape). "
        "xmpuzzle: a BurrTools puzzle (OUT/NAME.xmpuzzle) with the pieces, the shape and this "
        "assembly with its disassembly as the solution. An --out folder that holds an earlier "
        "export gets this one instead: its piece files of the same format that this export does not "
        "write (piece_07.stl ... of a larger puzzle) are removed and named in the log; other files "
        "stay.",
    )
    p.add_argument("assembly", help="assembly.json, a folder holding one, or a .puz file")
    p.add_argument("--format", required=True, choices=FORMATS)
    p.add_argument(
        "--voxel-size",
        type=_millimetres,
        default=10.0,
        metavar="MM",
        help="edge of one voxel in mm (default 10)",
    )
    p.add_argument(
        "--gap",
        type=_millimetres,
        default=PRINT_GAP,
        metavar="MM",
        help=f"clearance between neighbouring pieces in mm (default {PRINT_GAP:g}, for FDM "
        "printing; any gap > 0 parts voxels of a piece that touch only along an edge, so STL "
        "files stay watertight once a slicer welds vertices; 0: exact shape, and such STL "
        "edges are non-manifold)",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.set_defaults(func=cmd_export)
