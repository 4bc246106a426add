"""The `rllock bench` command group: every benchmark registers here, with the protocol flags of
`orchestration.cli.common` defined once. `add_commands(subparsers)` adds `bench` to the `rllock` parser.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Any

from tqdm import tqdm

from orchestration.bench import learning
from orchestration.cli.common import (
    add_protocol_args,
    add_simulations_arg,
    positive_float,
    ray_on_loopback_unless,
)
from orchestration.cli.flags import field_docs
from rllock.config import EVALUATION_MODES, SelfPlayConfig
from rllock.core.reference_checkers import REMOVAL_MODES
from rllock.errors import RLLockError

log = logging.getLogger("rllock")


def cmd_bench_checkers(args: argparse.Namespace) -> int:
    from orchestration.bench.solve import bench_checkers

    r = bench_checkers(
        shape=args.shape, pieces=args.pieces, piece=args.piece, seconds=args.seconds, removal=args.removal
    )
    if args.json:
        sys.stdout.write(
            json.dumps(
                {
                    **asdict(r),
                    "shape": args.shape,
                    "pieces": args.pieces,
                    "piece": args.piece,
                    "removal": args.removal,
                }
            )
            + "\n"
        )
    else:
        sys.stdout.write(
            f"checkers: {r.chunks_per_sec:,.0f} raw chunks sampled and checked per second "
            f"(median of {r.repeats} calls of 1024, one core), accept rate {r.accept_rate:.2%}, "
            f"piece {args.piece} of {args.shape} K={args.pieces}, removal={args.removal}\n"
        )
    return 0


def cmd_bench_solve(args: argparse.Namespace) -> int:
    from orchestration.bench.solve import bench_solve_task, format_solve_table, parse_tasks
    from rllock.search.solver import SearchConfig

    tasks = parse_tasks(args.tasks)
    rows = []
    for size, pieces in tqdm(tasks, desc="bench solve", unit="task", disable=None):
        rows.append(
            bench_solve_task(
                size,
                pieces,
                count=args.count,
                time_limit=args.time_limit,
                seed=args.seed,
                config=SearchConfig(),
            )
        )
        log.info("%s: %d found in %.1f s", rows[-1].task, rows[-1].found, rows[-1].seconds)
    if args.json:
        sys.stdout.write(
            json.dumps(
                {"time_limit_s": args.time_limit, "count": args.count, "tasks": [asdict(r) for r in rows]}
            )
            + "\n"
        )
    else:
        sys.stdout.write(format_solve_table(rows, args.time_limit) + "\n")
    return 0


def table_out(args: argparse.Namespace) -> Path | None:
    """The --out file of a table bench, checked before the bench runs so that its results are not lost."""
    out = Path(args.out) if args.out else None
    if out is not None and out.parent and not out.parent.is_dir():
        raise RLLockError(f"--out {out}: no such folder {out.parent}")
    return out


def emit_table(args: argparse.Namespace, out: Path | None, table: str, rows: list[dict]) -> None:
    """A table bench's results: the rows as JSON (--json) or the markdown table, and the table in --out."""
    sys.stdout.write(json.dumps(rows) + "\n" if args.json else table)
    if out is not None:
        out.write_text(table)


def task_table(args: argparse.Namespace, name: str, tasks: list, bench_one, format_table, row_json) -> int:
    """A table bench (paper, transfer): `bench_one(task, **protocol)` per task, then the table."""
    out = table_out(args)
    protocol = dict(count=args.count, batch=args.batch, time_limit=args.time_limit)
    rows = [
        bench_one(task, seed=args.seed, **protocol) for task in tqdm(tasks, desc=f"bench {name}", unit="task")
    ]
    table = format_table(rows, protocol, " ".join(["rllock", *sys.argv[1:]]))
    emit_table(args, out, table, [row_json(r) for r in rows])
    return 0


def cmd_bench_paper(args: argparse.Namespace) -> int:
    from orchestration.bench.paper import bench_paper_task, format_paper_table, parse_paper_tasks, row_json

    tasks = parse_paper_tasks(args.tasks)
    return task_table(args, "paper", tasks, bench_paper_task, format_paper_table, row_json)


def cmd_bench_transfer(args: argparse.Namespace) -> int:
    from functools import partial

    from orchestration.bench.transfer import (
        bench_transfer_task,
        format_transfer_table,
        multitask_checkpoint,
        parse_transfer_tasks,
        row_json,
    )
    from rllock.search.inference import check_simulations

    tasks = parse_transfer_tasks(args.tasks)
    checkpoint = multitask_checkpoint(args.checkpoint)  # a wrong checkpoint is an error before any work
    check_simulations(args.simulations)
    bench_one = partial(bench_transfer_task, checkpoint, simulations=args.simulations)
    return task_table(args, "transfer", tasks, bench_one, format_transfer_table, row_json)


def cmd_bench_ablation(args: argparse.Namespace) -> int:
    from orchestration.bench.ablation import ablation_cell, format_ablation_table, parse_ablation_tasks
    from rllock.config import METHODS

    tasks = parse_ablation_tasks(args.tasks)
    root = Path(args.runs)
    if not root.is_dir():
        raise RLLockError(f"--runs {root}: no such folder (it holds METHOD/TASK training runs)")
    out = table_out(args)
    cells = []
    for task in tqdm(tasks, desc="bench ablation", unit="task"):
        for method in METHODS:
            cells.append(
                ablation_cell(
                    root,
                    method,
                    task,
                    count=args.count,
                    batch=args.batch,
                    time_limit=args.time_limit,
                    seed=args.seed,
                )
            )
    table = format_ablation_table(cells, args.time_limit, " ".join(["rllock", *sys.argv[1:]]))
    emit_table(args, out, table, [{**asdict(c), "minutes_per_valid": c.minutes_per_valid} for c in cells])
    return 0


def cmd_bench_selfplay(args: argparse.Namespace) -> int:
    try:
        counts = [int(c) for c in args.actors.split(",")]
    except ValueError:
        raise RLLockError(f"--actors takes a comma-separated list of counts, got {args.actors!r}") from None
    if min(counts) < 1 or args.episodes_per_batch < 1 or args.simulations < 1:
        raise RLLockError("--actors, --episodes-per-batch and --simulations must be at least 1")
    ray_on_loopback_unless(None)
    from orchestration.bench.selfplay import bench_selfplay
    from rllock.config import MCTSConfig, NetConfig
    from rllock.core.env import make_task
    from rllock.search.network import fit_canvas

    task = make_task(args.shape, args.pieces)
    net = fit_canvas(task, NetConfig(canvas=args.canvas))
    rows = bench_selfplay(
        task,
        net,
        MCTSConfig(simulations=args.simulations),
        SelfPlayConfig(episodes_per_batch=args.episodes_per_batch, evaluation=args.evaluation),
        counts,
        args.seconds,
    )
    if args.json:
        sys.stdout.write(
            json.dumps(
                {
                    "shape": args.shape,
                    "pieces": args.pieces,
                    "canvas": net.canvas,
                    "simulations": args.simulations,
                    "rows": rows,
                }
            )
            + "\n"
        )
    else:
        base = rows[0]["episodes_per_sec"]
        for r in rows:
            split = ", ".join(f"{k} {v:.2f}" for k, v in r["ms_per_simulation"].items())
            sys.stdout.write(
                f"{r['actors']} actor(s) ({r['mode']}, {r['threads_per_actor']} thread(s) each): "
                f"{r['episodes_per_sec']:.3f} episodes/s, {r['simulations_per_sec']:.0f} simulations/s, "
                f"x{r['episodes_per_sec'] / base:.2f} vs {rows[0]['actors']}; ms per simulation "
                f"and episode row: {split}\n"
            )
    return 0


def _counts(text: str, flag: str) -> tuple[int, ...]:
    try:
        counts = tuple(int(c) for c in text.split(","))
    except ValueError:
        raise RLLockError(f"{flag} takes a comma-separated list of counts, got {text!r}") from None
    if min(counts) < 1:
        raise RLLockError(f"{flag} counts must be at least 1")
    return counts


def cmd_bench_scaling(args: argparse.Namespace) -> int:
    ray_on_loopback_unless(None)  # the bench's nodes all on 127.0.0.1
    import dataclasses

    from orchestration.bench.scaling import PRESETS, bench_scaling, format_scaling

    plan = PRESETS[args.preset]
    changes: dict[str, Any] = {
        name: value
        for name, value in (
            ("shape", args.shape),
            ("pieces", args.pieces),
            ("simulations", args.simulations),
            ("episodes_per_batch", args.episodes_per_batch),
            ("actors", args.actors and _counts(args.actors, "--actors")),
            ("nodes", args.nodes and _counts(args.nodes, "--nodes")),
            ("seconds", args.seconds),
            ("learner_steps", args.learner_steps),
        )
        if value is not None
    }
    result = bench_scaling(dataclasses.replace(plan, **changes))
    sys.stdout.write(json.dumps(result) + "\n" if args.json else format_scaling(result))
    return 0


def cmd_bench_shapes(args: argparse.Namespace) -> int:
    from orchestration.bench.shapes import (
        PIECES,
        SHAPES,
        bench_shapes,
        format_shapes_table,
        rows_json,
        shape_tasks,
    )

    def listed(text: str, flag: str, choices: tuple[str, ...] | None = None) -> list[str]:
        items = [t.strip() for t in text.split(",") if t.strip()]
        bad = [t for t in items if choices is not None and t not in choices]
        if not items or bad:
            raise RLLockError(f"{flag}: expected a comma-separated list of {', '.join(choices or ())}")
        return items

    arms = listed(args.arms, "--arms", ("solver", "general"))
    removals = list(REMOVAL_MODES) if args.removal == "both" else [args.removal]
    # --mesh alone benches the mesh; otherwise the named shapes, by default the five large ones
    shapes = listed(args.shapes, "--shapes") if args.shapes else [] if args.mesh else list(SHAPES)
    tasks = shape_tasks(shapes, args.mesh, list(_counts(args.resolutions, "--resolutions")))
    rows = bench_shapes(
        tasks,
        list(_counts(args.pieces, "--pieces") if args.pieces else PIECES),
        removals=removals,
        arms=arms,
        time_limit=args.time_limit,
        seed=args.seed,
        batch=args.batch,
        simulations=args.simulations,
    )
    if args.json:
        sys.stdout.write(json.dumps({"time_limit_s": args.time_limit, "rows": rows_json(rows)}) + "\n")
    else:
        command = "rllock " + " ".join(sys.argv[1:])
        sys.stdout.write(format_shapes_table(rows, arms, command, args.time_limit))
    return 0


def add_table_bench_args(p: argparse.ArgumentParser, unit: str) -> None:
    """The paper's protocol per `unit` (arm or run) and the table's outputs, for bench paper and ablation."""
    add_protocol_args(p, count=5, time_limit=300.0, per=unit)
    p.add_argument("--json", action="store_true", help="print one JSON list")
    p.add_argument("--out", default=None, help="also write the markdown table to this file")


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    bench = subparsers.add_parser("bench", help="benchmarks").add_subparsers(dest="bench", required=True)
    _add_throughput(bench)
    _add_tables(bench)
    learning.add_commands(bench)


def _add_throughput(bench: argparse._SubParsersAction) -> None:
    """The speed benches: the compiled checkers, the solver on the paper's cubes, self-play."""
    p = bench.add_parser("checkers", help="raw chunks sampled and checked per second on one core")
    p.add_argument("--shape", default="cube6")
    p.add_argument("--pieces", type=int, default=25)
    p.add_argument("--piece", type=int, default=13, help="the piece being sampled (1-based)")
    p.add_argument("--removal", choices=REMOVAL_MODES, default="straight")
    p.add_argument("--seconds", type=positive_float, default=5.0)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_bench_checkers)

    p = bench.add_parser("solve", help="the nine paper tasks: time per valid assembly vs the paper")
    p.add_argument("--tasks", help="subset, e.g. 5^3:13,6^3:20")
    add_protocol_args(p, count=5, time_limit=120.0, batch=False, per="task")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_bench_solve)

    p = bench.add_parser("selfplay", help="self-play episodes and simulations per second for actor counts")
    p.add_argument("--actors", default="1,2", help="comma-separated actor counts")
    p.add_argument("--shape", default="cube4")
    p.add_argument("--pieces", type=int, default=9)
    p.add_argument("--seconds", type=positive_float, default=60.0, help="measured seconds per actor count")
    p.add_argument("--simulations", type=int, default=256)
    p.add_argument("--canvas", type=int, default=None, help="default: the smallest that fits the shape")
    p.add_argument("--episodes-per-batch", type=int, default=8)
    p.add_argument(
        "--evaluation",
        choices=EVALUATION_MODES,
        default="auto",
        help=field_docs(SelfPlayConfig).get("evaluation"),
    )
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_bench_selfplay)

    p = bench.add_parser(
        "scaling",
        help="episodes and learner steps per second for actor counts, on one Ray node and on several",
    )
    p.add_argument(
        "--preset",
        choices=("small", "workstation"),
        default="small",
        help="small: cube4 K=7, 1 and 2 actors on 1 and 3 nodes, about 3 minutes on 2 cores; workstation: "
        "6^3 K=25 at 256 simulations, 1-15 actors, the learner on the GPU against the CPU (actor counts "
        "are capped at this machine's cores less one); the flags below change the preset's values",
    )
    p.add_argument("--shape")
    p.add_argument("--pieces", type=int)
    p.add_argument("--simulations", type=int)
    p.add_argument("--episodes-per-batch", type=int)
    p.add_argument("--actors", help="comma-separated actor counts")
    p.add_argument("--nodes", help="comma-separated node counts (1: one node with every core)")
    p.add_argument("--seconds", type=positive_float, help="each timed window")
    p.add_argument("--learner-steps", type=int, help="timed steps of the learner alone, per platform")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_bench_scaling)

    p = bench.add_parser(
        "shapes", help="large shapes swept over K: time to the first valid assembly, solver and general"
    )
    p.add_argument(
        "--shapes",
        default=None,
        help="comma-separated shape names (default: desia-bunny, desia-dog, mario, bunny, spider)",
    )
    p.add_argument("--mesh", default=None, help="an .stl/.obj model to add, at each of --resolutions")
    p.add_argument("--resolutions", default="12,16,20", help="the mesh's resolutions")
    p.add_argument("--pieces", default=None, help="the K sweep (default 10,20,...,100; K > N skipped)")
    p.add_argument("--removal", choices=(*REMOVAL_MODES, "both"), default="straight")
    # Defaults sized for a first run on 2 cores (the solver's cells, a minute at most each); the issue's
    # sweep (docs/benchmarks.md) gives --arms solver,general --time-limit 300.
    p.add_argument(
        "--arms", default="solver", help="solver, general, or both, comma-separated (default solver)"
    )
    p.add_argument(
        "--time-limit", type=positive_float, default=60.0, help="seconds per arm and task (default 60)"
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--batch", type=int, default=16, help="general's lockstep episodes per round")
    add_simulations_arg(p, " for general")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_bench_shapes)


def _add_tables(bench: argparse._SubParsersAction) -> None:
    """The table benches, each under the paper's protocol per arm or run."""
    p = bench.add_parser(
        "paper", help="the paper's tasks: shipped checkpoints, untrained search and solver, beside the paper"
    )
    p.add_argument(
        "--tasks", default=None, help="comma-separated names, e.g. cube4-k9,sofa-k19 (default: all)"
    )
    add_table_bench_args(p, "arm")
    p.set_defaults(func=cmd_bench_paper)

    p = bench.add_parser(
        "ablation", help="the paper's Table 1: the three methods' training and inference times, from runs"
    )
    p.add_argument(
        "--runs",
        default="runs/ablation",
        help="folder of training runs named METHOD/TASK (default runs/ablation)",
    )
    p.add_argument("--tasks", default=None, help="default: cube4-k7,cube4-k8,cube4-k9,cube5-k13")
    add_table_bench_args(p, "run")
    p.set_defaults(func=cmd_bench_ablation)

    p = bench.add_parser(
        "transfer",
        help="a multi-task checkpoint zero-shot, against untrained, per-task checkpoints and the solver",
    )
    p.add_argument(
        "--checkpoint", required=True, help="a multi-task run's folder or a shipped name (general)"
    )
    p.add_argument(
        "--tasks",
        default=None,
        help="SHAPE:K list, e.g. sofa:12,cube4:9 (default: the held-out set, bench/transfer.py's HELD_OUT)",
    )
    add_simulations_arg(p, " in the zero-shot and untrained arms")
    add_table_bench_args(p, "arm")
    p.set_defaults(func=cmd_bench_transfer)
