"""Each `rllock bench` command: parse its lists, run its bench (imported only when it runs, so that the
parser stays light) and print the result. `rllock.orchestration.bench.commands` registers them all."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

from tqdm import tqdm

from rllock.config import SelfPlayConfig
from rllock.core.reference_checkers import REMOVAL_MODES
from rllock.errors import RLLockError
from rllock.orchestration.bench.learning import ArmRow, learning_ratio
from rllock.orchestration.bench.specs import choices, counts, items
from rllock.orchestration.cli.common import load_for, ray_on_loopback_unless

log = logging.getLogger("rllock")


def cmd_bench_checkers(args: argparse.Namespace) -> int:
    from rllock.orchestration.bench.solve import bench_checkers

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
    from rllock.orchestration.bench.solve import bench_solve_task, format_solve_table, parse_tasks
    from rllock.search.search_config import SearchConfig

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
    from rllock.orchestration.bench.paper import (
        bench_paper_task,
        format_paper_table,
        parse_paper_tasks,
        row_json,
    )

    tasks = parse_paper_tasks(args.tasks)
    return task_table(args, "paper", tasks, bench_paper_task, format_paper_table, row_json)


def cmd_bench_transfer(args: argparse.Namespace) -> int:
    from functools import partial

    from rllock.orchestration.bench.transfer import (
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
    from rllock.config import METHODS
    from rllock.orchestration.bench.ablation import ablation_cell, format_ablation_table, parse_ablation_tasks

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
    actors = counts(args.actors, "--actors")
    if args.episodes_per_batch < 1 or args.simulations < 1:
        raise RLLockError("--actors, --episodes-per-batch and --simulations must be at least 1")
    ray_on_loopback_unless(None)
    from rllock.config import MCTSConfig, NetConfig
    from rllock.core.env import make_task
    from rllock.orchestration.bench.selfplay import bench_selfplay
    from rllock.search.network import fit_canvas

    task = make_task(args.shape, args.pieces)
    net = fit_canvas(task, NetConfig(canvas=args.canvas))
    rows = bench_selfplay(
        task,
        net,
        MCTSConfig(simulations=args.simulations),
        SelfPlayConfig(episodes_per_batch=args.episodes_per_batch, evaluation=args.evaluation),
        list(actors),
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


def cmd_bench_scaling(args: argparse.Namespace) -> int:
    ray_on_loopback_unless(None)  # the bench's nodes all on 127.0.0.1
    import dataclasses

    from rllock.orchestration.bench.scaling import PRESETS, bench_scaling, format_scaling

    plan = PRESETS[args.preset]
    changes: dict[str, Any] = {
        name: value
        for name, value in (
            ("shape", args.shape),
            ("pieces", args.pieces),
            ("simulations", args.simulations),
            ("episodes_per_batch", args.episodes_per_batch),
            ("actors", args.actors and counts(args.actors, "--actors")),
            ("nodes", args.nodes and counts(args.nodes, "--nodes")),
            ("seconds", args.seconds),
            ("learner_steps", args.learner_steps),
            ("features", args.features and counts(args.features, "--features")),
        )
        if value is not None
    }
    result = bench_scaling(dataclasses.replace(plan, **changes))
    sys.stdout.write(json.dumps(result) + "\n" if args.json else format_scaling(result))
    return 0


def cmd_bench_shapes(args: argparse.Namespace) -> int:
    from rllock.orchestration.bench.shapes import (
        PIECES,
        SHAPES,
        bench_shapes,
        format_shapes_table,
        rows_json,
        shape_tasks,
        solver_arm,
    )

    named = choices(args.arms, "--arms", ("solver", "general"))
    layouts = [(w, 1) for w in counts(args.workers, "--workers")]
    layouts += [(1, t) for t in counts(args.threads, "--threads") if (1, t) not in layouts]
    arms = [
        a for name in named for a in ([solver_arm(*wt) for wt in layouts] if name == "solver" else [name])
    ]
    removals = list(REMOVAL_MODES) if args.removal == "both" else [args.removal]
    # --mesh alone benches the mesh; otherwise the named shapes, by default the five large ones
    shapes = items(args.shapes, "--shapes") if args.shapes else [] if args.mesh else list(SHAPES)
    tasks = shape_tasks(shapes, args.mesh, list(counts(args.resolutions, "--resolutions")))
    rows = bench_shapes(
        tasks,
        list(counts(args.pieces, "--pieces") if args.pieces else PIECES),
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


def cmd_bench_learning(args: argparse.Namespace) -> int:
    from rllock.search.inference import generate, untrained_like

    trained = load_for(args)
    rows: dict[str, ArmRow] = {}
    for name, policy in (("trained", trained), ("untrained", untrained_like(trained, args.seed))):
        r = generate(policy, count=args.count, batch=args.batch, time_limit=args.time_limit, seed=args.seed)
        rows[name] = {
            "valid": r.valid,
            "episodes": r.episodes,
            "seconds": r.seconds,
            "success_rate": r.success_rate,
            "time_per_valid_s": r.time_per_valid_s,
        }
        log.info("%s: %d valid of %d episodes in %.1f s", name, r.valid, r.episodes, r.seconds)
    t, u = rows["trained"]["time_per_valid_s"], rows["untrained"]["time_per_valid_s"]
    ratio, bound = learning_ratio(t, u, rows["untrained"]["seconds"])
    doc = {
        "checkpoint": trained.source,
        "step": trained.step,
        "task": f"{trained.task.shape_name} K={trained.task.pieces}",
        **rows,
        "ratio_trained_over_untrained": ratio,
        "ratio_upper_bound": bound,
    }
    if args.json:
        sys.stdout.write(json.dumps(doc) + "\n")
    else:

        def fmt(v):
            return "none found" if v is None else f"{v:.2f} s"

        sys.stdout.write(
            f"learning ({doc['task']}, step {trained.step}, batches of {args.batch}, seed {args.seed}):\n"
            f"  trained:   {fmt(t)} per valid, success rate {100 * rows['trained']['success_rate']:.1f}% "
            f"({rows['trained']['valid']}/{rows['trained']['episodes']})\n"
            f"  untrained: {fmt(u)} per valid, success rate {100 * rows['untrained']['success_rate']:.1f}% "
            f"({rows['untrained']['valid']}/{rows['untrained']['episodes']})\n"
            f"  ratio trained/untrained: {'-' if ratio is None else f'{ratio:.3f}'}"
            f"{'' if bound is None else f' (below {bound:.3f}: the untrained arm found none)'}\n"
        )
    return 0


def cmd_bench_success(args: argparse.Namespace) -> int:
    from rllock.search.inference import success_rate

    # Every checkpoint is loaded (and checked) before any is played: a bad one fails at once.
    policies = [load_for(argparse.Namespace(**{**vars(args), "checkpoint": c})) for c in args.checkpoint]
    rows = []
    for policy in policies:
        r = success_rate(policy, episodes=args.episodes, batch=args.batch, seed=args.seed)
        low, high = r.interval()
        rows.append(
            {
                "checkpoint": policy.source,
                "step": policy.step,
                "task": f"{policy.task.shape_name} K={policy.task.pieces}",
                "canvas": policy.net.canvas,
                "simulations": policy.mcts.simulations,
                "valid": r.valid,
                "episodes": r.episodes,
                "success_rate": r.rate,
                "interval_95": [low, high],
                "seconds": r.seconds,
            }
        )
        log.info("%s: %d valid of %d episodes in %.1f s", policy.source, r.valid, r.episodes, r.seconds)
    if args.json:
        sys.stdout.write(json.dumps(rows) + "\n")
        return 0
    lines = [
        f"success rate (batches of {args.batch}, seed {args.seed}, the same episodes' seeds for each):",
        "| checkpoint | step | task | canvas | simulations | valid / episodes | success | 95% interval | s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        low, high = row["interval_95"]
        lines.append(
            f"| {row['checkpoint']} | {row['step']} | {row['task']} | {row['canvas']} | "
            f"{row['simulations']} | {row['valid']} / {row['episodes']} | {100 * row['success_rate']:.1f}% | "
            f"{100 * low:.1f}-{100 * high:.1f}% | {row['seconds']:.0f} |"
        )
    sys.stdout.write("\n".join(lines) + "\n")
    return 0


def cmd_bench_guide(args: argparse.Namespace) -> int:
    from rllock.orchestration.bench.guide import bench_guide, format_guide_table, parse_cells, rows_json
    from rllock.search.guide_checkpoint import load_guide
    from rllock.search.search_config import SearchConfig

    cells = parse_cells(args.cells)
    arms = choices(args.arms, "--arms", ("solver", "guided", "untrained"))
    seeds = [int(s) for s in items(args.seeds, "--seeds") if s.isdigit()]
    if len(seeds) != len(items(args.seeds, "--seeds")):
        raise RLLockError(f"--seeds takes a comma-separated list of seeds (0, 1, ...), got {args.seeds!r}")
    config = SearchConfig()
    if args.dives is not None and args.dives < 1:
        raise RLLockError(f"--dives must be at least 1, got {args.dives}")
    if args.dive_share is not None and not args.dive_share >= 0:
        raise RLLockError(f"--dive-share must be at least 0, got {args.dive_share}")
    if args.untrained_seed < 0:
        raise RLLockError(f"--untrained-seed must be at least 0, got {args.untrained_seed}")
    config = replace(
        config,
        dives=config.dives if args.dives is None else args.dives,
        dive_share=config.dive_share if args.dive_share is None else args.dive_share,
    )
    guide = load_guide(args.guide)  # a bad checkpoint is an error before any search
    rows = bench_guide(
        cells,
        guide,
        seeds=seeds,
        arms=arms,
        time_limit=args.time_limit,
        config=config,
        untrained_seed=args.untrained_seed,
    )
    if args.json:
        doc = {
            "time_limit_s": args.time_limit,
            "untrained_seed": args.untrained_seed,
            "rows": rows_json(rows),
        }
        sys.stdout.write(json.dumps(doc) + "\n")
    else:
        command = "rllock " + " ".join(sys.argv[1:])
        sys.stdout.write(format_guide_table(rows, arms, guide, command, args.time_limit, args.untrained_seed))
    return 0


def cmd_bench_serve(args: argparse.Namespace) -> int:
    import os

    from rllock.orchestration.bench.serve import format_load_table, load_test

    if args.jobs < 1:
        raise RLLockError(f"--jobs must be at least 1, got {args.jobs}")
    if args.max_jobs < 0:
        raise RLLockError(f"--max-jobs must be >= 0, got {args.max_jobs}")
    max_jobs = args.max_jobs or 2 * (os.cpu_count() or 1)
    arms, up = load_test(
        jobs=args.jobs, shape=args.shape, pieces=args.pieces, time_limit=args.time_limit, max_jobs=max_jobs
    )
    if args.json:
        sys.stdout.write(
            json.dumps({"server_up_s": round(up, 2), "arms": [a.to_json() for a in arms]}) + "\n"
        )
    else:
        sys.stdout.write(format_load_table(arms, "rllock " + " ".join(sys.argv[1:]), up))
    return 0 if all(a.verified == a.jobs for a in arms) else 1
