"""The `rllock` command line. Bad input ends in one line on stderr and exit status 2."""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from dataclasses import asdict
from pathlib import Path

from tqdm import tqdm

from orchestration.cli.assemblies import add_commands as add_result_commands
from orchestration.cli.flags import add_flags, field_docs, from_flags
from rllock.config import EVALUATION_MODES, METHODS, SelfPlayConfig, TrainConfig
from rllock.core.reference_checkers import REMOVAL_MODES
from rllock.errors import RLLockError
from rllock.files.assembly import read_assembly, write_assembly

log = logging.getLogger("rllock")


def _positive_float(text: str) -> float:
    value = float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text}")
    return value


def _add_task_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--shape",
        required=True,
        help="cubeN, box:WxHxD, ring, a .puz/.vol/.npy file, or a closed .stl/.obj mesh",
    )
    p.add_argument(
        "--resolution",
        type=int,
        default=None,
        help="for .stl/.obj shapes: at most this many voxels along the longest side (default 8)",
    )
    p.add_argument("--pieces", "-K", type=int, required=True, help="piece count K")
    p.add_argument(
        "--removal",
        choices=REMOVAL_MODES,
        default="straight",
        help="straight: one axis slide per piece (default); path: DESIA's multi-move test",
    )
    p.add_argument("--seed", type=int, default=0)


def _assemblies(count: int) -> str:
    return "assembly" if count == 1 else "assemblies"


def _fresh_out(path: str) -> Path:
    """An output folder that holds no earlier results (they would be overwritten or mixed up)."""
    out = Path(path)
    if out.exists() and (not out.is_dir() or any(out.glob("assembly_*"))):
        raise RLLockError(f"--out {out} already holds results; choose another folder")
    return out


def cmd_verify(args: argparse.Namespace) -> int:
    from rllock.core.verifier import verify_labels

    labels, meta = read_assembly(args.file)
    verdict = verify_labels(labels, args.removal or meta.get("removal") or "straight")
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


def _picture():
    from rllock.files.render import write_picture  # matplotlib: loaded only where pictures are drawn

    return write_picture


def cmd_solve(args: argparse.Namespace) -> int:
    from rllock.core.env import make_task
    from rllock.search.solver import SearchConfig, search

    task = make_task(args.shape, args.pieces, args.removal, resolution=args.resolution)
    config = SearchConfig()
    out = _fresh_out(args.out)
    picture = _picture()
    start = time.perf_counter()
    found = 0
    with tqdm(
        total=args.count, desc=f"solve {task.shape_name} K={task.pieces}", unit="assembly", disable=None
    ) as bar:
        for f in search(task, seed=args.seed, time_limit=args.time_limit, config=config):
            found += 1
            folder = out / f"assembly_{found:03d}"
            write_assembly(
                folder,
                f.labels,
                removal=task.removal,
                shape=task.shape_name,
                method={"name": "search", **asdict(config)},
                seed=args.seed,
                timings={"seconds": round(f.seconds, 4), "node_expansions": f.expansions},
                picture=picture,
            )
            log.info("wrote %s (%.2f s)", folder, f.seconds)
            bar.update(1)
            if found >= args.count:
                break
    elapsed = time.perf_counter() - start
    if found == 0:
        sys.stdout.write(
            f"solve: no valid assembly of {task.shape_name} K={task.pieces} within {args.time_limit:g} s\n"
        )
        return 1
    sys.stdout.write(
        f"solve: {found} valid {_assemblies(found)} of {task.shape_name} K={task.pieces} in {elapsed:.2f} s: "
        f"{elapsed / found:.3f} s per valid assembly -> {out}\n"
    )
    return 0


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


def _ray_on_loopback_unless(address: str | None) -> None:
    """A Ray instance started here serves this machine only: bind it to loopback, not to the host's
    outward address (Ray reads this setting when it is imported). A cluster run keeps Ray's default."""
    if not address:
        os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")


def cmd_train(args: argparse.Namespace) -> int:
    if args.resume:
        from rllock.files.checkpoint import run_config

        config = run_config(Path(args.resume), minutes=args.minutes, max_learner_steps=args.max_learner_steps)
    else:
        config = from_flags(TrainConfig, args)
        config.validate()
    _ray_on_loopback_unless(config.address)
    from orchestration.train import train

    result = train(config, resume=bool(args.resume))
    if result["interrupted"]:
        sys.stdout.write(
            f"train: stopped at learner step {result['steps']}; resume with: "
            f"rllock train --resume {result['logdir']}\n"
        )
        return 130
    val = result["validation"]
    last = "none (it did not fit the budget)" if val is None else f"{100 * val['success_rate']:.1f}% valid"
    best = result["best_success_rate"]
    sys.stdout.write(
        f"train: {result['steps']} learner steps, {result['episodes']} self-play episodes "
        f"({result['episodes_per_sec']:.2f}/s, {result['simulations_per_sec']:.0f} simulations/s) in "
        f"{result['seconds']:.0f} s; last validation {last}, best "
        f"{'none yet' if best < 0 else f'{100 * best:.1f}%'}\n"
        f"checkpoints: {result['logdir']}/best (best validated) and {result['logdir']}/checkpoints (latest)\n"
        f"watch it: tensorboard --logdir {result['logdir']}\n"
    )
    return 0


def _expected_task(args: argparse.Namespace, saved: dict) -> dict | None:
    """The identity of the task named on the command line (if one was named), to compare with the
    checkpoint's task `saved`; an unnamed removal mode is the checkpoint's own."""
    if args.shape is None and args.pieces is None:
        return None
    if args.shape is None or args.pieces is None:
        raise RLLockError("give both --shape and --pieces to check the checkpoint's task, or neither")
    from rllock.core.env import make_task
    from rllock.files.checkpoint import task_identity

    task = make_task(args.shape, args.pieces, args.removal or saved["removal"], resolution=args.resolution)
    return task_identity(task, saved["canvas"])


def _load_for(args: argparse.Namespace):
    """The policy for `generate`, `bench learning` and `bench success`: a single-task checkpoint's own
    task (checked against --shape and --pieces when named), or the named task for a multi-task
    checkpoint; searching with --simulations when given."""
    from rllock.core.env import make_task
    from rllock.files.checkpoint import find_step_dir, read_meta
    from rllock.search.inference import is_multitask, load_policy, with_simulations

    if args.batch < 1:
        raise RLLockError(f"--batch must be at least 1, got {args.batch}")
    meta = read_meta(find_step_dir(Path(args.checkpoint)))
    task, expect = None, None
    if is_multitask(meta):
        if args.shape is None or args.pieces is None:
            raise RLLockError(
                f"checkpoint {args.checkpoint} serves many tasks: name one with --shape and --pieces"
            )
        removal = args.removal or meta["task"]["removal"]
        task = make_task(args.shape, args.pieces, removal, resolution=args.resolution)
    else:
        expect = _expected_task(args, meta["task"])
    return with_simulations(load_policy(args.checkpoint, expect, task=task), args.simulations)


def cmd_generate(args: argparse.Namespace) -> int:
    out = _fresh_out(args.out)
    if args.actors < 0:
        raise RLLockError(f"--actors must be >= 0, got {args.actors}")
    if args.address and not args.actors:
        raise RLLockError("--address needs --actors N: generation joins a Ray cluster only with actors")
    policy = _load_for(args)
    settings = dict(
        count=args.count,
        batch=args.batch,
        time_limit=args.time_limit,
        seed=args.seed,
        out=out,
        picture=_picture(),
    )
    if args.actors:
        _ray_on_loopback_unless(args.address)
        from orchestration.generate import generate_on_ray

        result = generate_on_ray(policy, actors=args.actors, address=args.address, **settings)
    else:
        from rllock.search.inference import generate

        result = generate(policy, **settings)
    task = policy.task
    if result.valid == 0:
        sys.stdout.write(
            f"generate: no valid assembly of {task.shape_name} K={task.pieces} in {result.episodes} "
            f"episodes ({result.seconds:.1f} s)\n"
        )
        return 1
    sys.stdout.write(
        f"generate: {result.valid} valid {_assemblies(result.valid)} of {task.shape_name} K={task.pieces} "
        f"from "
        f"{result.episodes} episodes in {result.seconds:.1f} s: {result.time_per_valid_s:.2f} s per "
        f"valid assembly -> {args.out}\n"
    )
    return 0


def learning_ratio(
    trained: float | None, untrained: float | None, untrained_seconds: float
) -> tuple[float | None, float | None]:
    """(trained / untrained time per valid assembly, an upper bound on it when only the untrained arm
    found nothing: having found none in S seconds, it needs more than S per valid assembly)."""
    if trained is None:
        return None, None
    if untrained is None:
        return None, trained / untrained_seconds
    return trained / untrained, None


def cmd_bench_learning(args: argparse.Namespace) -> int:
    from rllock.search.inference import generate, untrained_like

    trained = _load_for(args)
    rows = {}
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
    policies = [_load_for(argparse.Namespace(**{**vars(args), "checkpoint": c})) for c in args.checkpoint]
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
    for r in rows:
        low, high = r["interval_95"]
        lines.append(
            f"| {r['checkpoint']} | {r['step']} | {r['task']} | {r['canvas']} | {r['simulations']} | "
            f"{r['valid']} / {r['episodes']} | {100 * r['success_rate']:.1f}% | "
            f"{100 * low:.1f}-{100 * high:.1f}% | {r['seconds']:.0f} |"
        )
    sys.stdout.write("\n".join(lines) + "\n")
    return 0


def _table_out(args: argparse.Namespace) -> Path | None:
    """The --out file of a table bench, checked before the bench runs so that its results are not lost."""
    out = Path(args.out) if args.out else None
    if out is not None and out.parent and not out.parent.is_dir():
        raise RLLockError(f"--out {out}: no such folder {out.parent}")
    return out


def _emit_table(args: argparse.Namespace, out: Path | None, table: str, rows: list[dict]) -> None:
    """A table bench's results: the rows as JSON (--json) or the markdown table, and the table in --out."""
    sys.stdout.write(json.dumps(rows) + "\n" if args.json else table)
    if out is not None:
        out.write_text(table)


def _task_table(args: argparse.Namespace, name: str, tasks: list, bench_one, format_table, row_json) -> int:
    """A table bench (paper, transfer): `bench_one(task, **protocol)` per task, then the table."""
    out = _table_out(args)
    protocol = dict(count=args.count, batch=args.batch, time_limit=args.time_limit)
    rows = [
        bench_one(task, seed=args.seed, **protocol) for task in tqdm(tasks, desc=f"bench {name}", unit="task")
    ]
    table = format_table(rows, protocol, " ".join(["rllock", *sys.argv[1:]]))
    _emit_table(args, out, table, [row_json(r) for r in rows])
    return 0


def cmd_bench_paper(args: argparse.Namespace) -> int:
    from orchestration.bench.paper import bench_paper_task, format_paper_table, parse_paper_tasks, row_json

    tasks = parse_paper_tasks(args.tasks)
    return _task_table(args, "paper", tasks, bench_paper_task, format_paper_table, row_json)


def cmd_bench_transfer(args: argparse.Namespace) -> int:
    from functools import partial

    from orchestration.bench.transfer import (
        bench_transfer_task,
        format_transfer_table,
        multitask_meta,
        parse_transfer_tasks,
        row_json,
    )
    from rllock.search.inference import check_simulations

    tasks = parse_transfer_tasks(args.tasks)
    multitask_meta(args.checkpoint)  # a wrong checkpoint is an error before any work
    check_simulations(args.simulations)
    bench_one = partial(bench_transfer_task, args.checkpoint, simulations=args.simulations)
    return _task_table(args, "transfer", tasks, bench_one, format_transfer_table, row_json)


def cmd_bench_ablation(args: argparse.Namespace) -> int:
    from orchestration.bench.ablation import ablation_cell, format_ablation_table, parse_ablation_tasks
    from rllock.config import METHODS

    tasks = parse_ablation_tasks(args.tasks)
    root = Path(args.runs)
    if not root.is_dir():
        raise RLLockError(f"--runs {root}: no such folder (it holds METHOD/TASK training runs)")
    out = _table_out(args)
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
    _emit_table(args, out, table, [{**asdict(c), "minutes_per_valid": c.minutes_per_valid} for c in cells])
    return 0


def cmd_pretrained(args: argparse.Namespace) -> int:
    from rllock.files.checkpoint import shipped_names
    from rllock.search import pretrained

    if args.ship is not None:
        if args.name is None:
            raise RLLockError("--ship needs --name, the name to ship the checkpoint under (e.g. cube4-k9)")
        target = pretrained.ship(Path(args.ship), args.name)
        size = sum(f.stat().st_size for f in target.rglob("*") if f.is_file())
        sys.stdout.write(f"shipped {args.name}: {target} ({size / 2**20:.1f} MiB)\n")
        return 0
    rows = [pretrained.describe(name) for name in shipped_names()]
    if args.json:
        sys.stdout.write(json.dumps(rows) + "\n")
        return 0
    if not rows:
        sys.stdout.write("no shipped checkpoints\n")
        return 0

    def rate(row: dict) -> str:
        if row["validation_success"] is None:
            return "-"
        return f"{100 * row['validation_success']:.1f}% of {row['validation_episodes']}"

    lines = [
        "| name | task | canvas | simulations | training (min) | trained on | learner steps "
        "| validation success | commit |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        commit = (r["commit"] or "-")[:12]
        minutes = f"{r['training_minutes']} from {r['init']}" if r["init"] else r["training_minutes"]
        lines.append(
            f"| {r['name']} | {r['task']} | {r['canvas']} | {r['simulations']} | {minutes} | "
            f"{pretrained.machine_summary(r['machine'])} | {r['learner_steps']} | {rate(r)} | {commit} |"
        )
    sys.stdout.write("\n".join(lines) + "\n")
    return 0


def cmd_bench_selfplay(args: argparse.Namespace) -> int:
    try:
        counts = [int(c) for c in args.actors.split(",")]
    except ValueError:
        raise RLLockError(f"--actors takes a comma-separated list of counts, got {args.actors!r}") from None
    if min(counts) < 1 or args.episodes_per_batch < 1 or args.simulations < 1:
        raise RLLockError("--actors, --episodes-per-batch and --simulations must be at least 1")
    _ray_on_loopback_unless(None)
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


def _add_simulations_arg(p: argparse.ArgumentParser, arms: str = "") -> None:
    p.add_argument(
        "--simulations",
        type=int,
        default=None,
        help=f"search simulations per decision{arms} (default: the checkpoint's own, as it was trained)",
    )


def _add_checkpoint_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--checkpoint",
        required=True,
        help="a training run's log directory (its best checkpoint), one checkpoint directory, or the name "
        "of a shipped checkpoint (rllock pretrained)",
    )
    p.add_argument("--count", type=int, default=5, help="valid assemblies to find")
    p.add_argument(
        "--batch", type=int, default=64, help="episodes per batch (one network call per simulation)"
    )
    p.add_argument("--time-limit", type=_positive_float, default=3600.0, help="seconds")
    p.add_argument("--seed", type=int, default=0)
    _add_task_args_for_checkpoints(p)


def _add_task_args_for_checkpoints(p: argparse.ArgumentParser) -> None:
    """The search budget and the task (`_load_for`): a multi-task checkpoint's task, or a check on a
    single-task checkpoint's own."""
    _add_simulations_arg(p)
    p.add_argument("--shape", default=None, help="optional: fail unless the checkpoint is for this shape")
    p.add_argument(
        "--pieces", type=int, default=None, help="optional: fail unless the checkpoint is for this K"
    )
    p.add_argument(
        "--removal",
        choices=REMOVAL_MODES,
        default=None,
        help="optional: fail unless the checkpoint uses this removal mode",
    )
    p.add_argument("--resolution", type=int, default=None, help="for a mesh --shape: as given to train")


def _add_table_bench_args(p: argparse.ArgumentParser, unit: str) -> None:
    """The paper's protocol per `unit` (arm or run) and the table's outputs, for bench paper and ablation."""
    p.add_argument("--count", type=int, default=5, help=f"valid assemblies to find per {unit}")
    p.add_argument("--batch", type=int, default=64, help="episodes per batch")
    p.add_argument("--time-limit", type=_positive_float, default=300.0, help=f"seconds per {unit}")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true", help="print one JSON list")
    p.add_argument("--out", default=None, help="also write the markdown table to this file")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rllock", description="Interlocking assemblies from voxel shapes.")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("verify", help="check every stage of an assembly (.puz or assembly.json)")
    p.add_argument("file")
    p.add_argument(
        "--removal",
        choices=REMOVAL_MODES,
        default=None,
        help="default: the mode an assembly.json names, else straight",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=cmd_verify)

    p = sub.add_parser("solve", help="find assemblies by randomized search (no training needed)")
    _add_task_args(p)
    p.add_argument("--count", type=int, default=1, help="valid assemblies to find")
    p.add_argument("--time-limit", type=_positive_float, default=60.0, help="seconds")
    p.add_argument("--out", required=True, help="folder; each assembly goes to OUT/assembly_NNN/")
    p.set_defaults(func=cmd_solve)

    bench = sub.add_parser("bench", help="benchmarks").add_subparsers(dest="bench", required=True)
    p = bench.add_parser("checkers", help="raw chunks sampled and checked per second on one core")
    p.add_argument("--shape", default="cube6")
    p.add_argument("--pieces", type=int, default=25)
    p.add_argument("--piece", type=int, default=13, help="the piece being sampled (1-based)")
    p.add_argument("--removal", choices=REMOVAL_MODES, default="straight")
    p.add_argument("--seconds", type=_positive_float, default=5.0)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_bench_checkers)

    p = bench.add_parser("solve", help="the nine paper tasks: time per valid assembly vs the paper")
    p.add_argument("--tasks", help="subset, e.g. 5^3:13,6^3:20")
    p.add_argument("--count", type=int, default=5, help="valid assemblies per task")
    p.add_argument("--time-limit", type=_positive_float, default=120.0, help="seconds per task")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_bench_solve)

    p = sub.add_parser("train", help="self-play training on Ray (local, or a cluster with --address)")
    add_flags(
        p,
        TrainConfig,
        required_unless="--resume",
        choices={"removal": REMOVAL_MODES, "evaluation": EVALUATION_MODES, "method": METHODS},
    )
    p.add_argument(
        "--resume",
        metavar="LOGDIR",
        default=None,
        help="continue the run in LOGDIR with its saved config; --minutes is the time to add, "
        "--max-learner-steps a new step limit",
    )
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("generate", help="assemblies from a trained checkpoint (batched MCTS)")
    _add_checkpoint_args(p)
    p.add_argument(
        "--actors",
        type=int,
        default=0,
        help="play the rounds on this many Ray actors, one core each (default 0: in this process, "
        "on all cores)",
    )
    p.add_argument("--address", default=None, help="with --actors: join this Ray cluster (HOST:PORT or auto)")
    p.add_argument("--out", required=True, help="folder; each assembly goes to OUT/assembly_NNN/")
    p.set_defaults(func=cmd_generate)

    p = bench.add_parser(
        "paper", help="the paper's tasks: shipped checkpoints, untrained search and solver, beside the paper"
    )
    p.add_argument(
        "--tasks", default=None, help="comma-separated names, e.g. cube4-k9,sofa-k19 (default: all)"
    )
    _add_table_bench_args(p, "arm")
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
    _add_table_bench_args(p, "run")
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
    _add_simulations_arg(p, " in the zero-shot and untrained arms")
    _add_table_bench_args(p, "arm")
    p.set_defaults(func=cmd_bench_transfer)

    p = bench.add_parser("learning", help="a checkpoint against the same search with an untrained network")
    _add_checkpoint_args(p)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_bench_learning)

    p = bench.add_parser(
        "success",
        help="checkpoints' success rates over many episodes, with 95%% intervals: a large validation",
    )
    p.add_argument(
        "--checkpoint",
        action="append",
        required=True,
        help="a run's log directory, one checkpoint directory or a shipped name; repeat to compare",
    )
    p.add_argument("--episodes", type=int, default=1024, help="at least this many episodes per checkpoint")
    p.add_argument("--batch", type=int, default=64, help="episodes per batch")
    p.add_argument("--seed", type=int, default=0)
    _add_task_args_for_checkpoints(p)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_bench_success)

    p = bench.add_parser("selfplay", help="self-play episodes and simulations per second for actor counts")
    p.add_argument("--actors", default="1,2", help="comma-separated actor counts")
    p.add_argument("--shape", default="cube4")
    p.add_argument("--pieces", type=int, default=9)
    p.add_argument("--seconds", type=_positive_float, default=60.0, help="measured seconds per actor count")
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

    p = sub.add_parser("pretrained", help="the trained checkpoints shipped with RL-Lock, by name")
    p.add_argument("--json", action="store_true", help="print one JSON list")
    p.add_argument(
        "--ship",
        metavar="LOGDIR",
        default=None,
        help="for maintainers: copy the best checkpoint of this run into the package (parameters only)",
    )
    p.add_argument("--name", default=None, help="with --ship: the name, e.g. cube4-k9")
    p.set_defaults(func=cmd_pretrained)

    add_result_commands(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
        force=True,
    )  # ray/absl install root handlers on import; ours must win
    for noisy in ("numba", "jax", "absl", "matplotlib", "PIL", "orbax", "ray"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    # A learner that sees a GPU takes at most this share of its memory (JAX preallocates 75% otherwise);
    # set the variable yourself to change it. JAX is imported later, by the commands that need it.
    os.environ.setdefault("XLA_PYTHON_CLIENT_MEM_FRACTION", "0.5")
    try:
        if getattr(args, "count", 1) < 1:
            raise RLLockError(f"--count must be at least 1, got {args.count}")
        return args.func(args)
    except RLLockError as exc:
        sys.stderr.write(f"rllock: error: {exc}\n")
        return 2
    except OSError as exc:  # unwritable or missing output paths, full disks: the system's own words
        sys.stderr.write(f"rllock: error: {exc.strerror or exc}: {exc.filename or ''}\n")
        return 2
    except KeyboardInterrupt:
        sys.stderr.write("rllock: interrupted\n")
        return 130


if __name__ == "__main__":
    sys.exit(main())
