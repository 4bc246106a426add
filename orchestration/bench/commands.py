"""The `rllock bench` command group: every bench registers here, its flags beside the others, with the
protocol flags of `rllock.orchestration.cli.common` defined once; its command is in
`rllock.orchestration.bench.entry`. `add_commands(subparsers)` adds `bench` to the `rllock` parser.
"""

from __future__ import annotations

import argparse

from rllock.config import EVALUATION_MODES, SelfPlayConfig
from rllock.core.reference_checkers import REMOVAL_MODES
from rllock.orchestration.bench import entry
from rllock.orchestration.cli.common import (
    add_checkpoint_args,
    add_checkpoint_task_args,
    add_protocol_args,
    add_simulations_arg,
    positive_float,
)
from rllock.orchestration.cli.flags import field_docs


def add_table_bench_args(p: argparse.ArgumentParser, unit: str) -> None:
    """The paper's protocol per `unit` (arm or run) and the table's outputs, for bench paper and ablation."""
    add_protocol_args(p, count=5, time_limit=300.0, per=unit)
    p.add_argument("--json", action="store_true", help="print one JSON list")
    p.add_argument("--out", default=None, help="also write the markdown table to this file")


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    bench = subparsers.add_parser("bench", help="benchmarks").add_subparsers(dest="bench", required=True)
    _add_throughput(bench)
    _add_tables(bench)
    _add_learning(bench)


def _add_throughput(bench: argparse._SubParsersAction) -> None:
    """The speed benches: the compiled checkers, the solver on the paper's cubes, self-play, scaling and
    large shapes."""
    _add_checkers_and_solve(bench)
    _add_selfplay(bench)
    _add_scaling(bench)
    _add_shapes(bench)
    _add_guide(bench)
    _add_serve(bench)


def _add_serve(bench: argparse._SubParsersAction) -> None:
    p = bench.add_parser(
        "serve",
        help="load test of rllock serve on loopback: generate jobs together against one after another",
    )
    p.add_argument("--jobs", type=int, default=16, help="generate jobs per arm (default %(default)s)")
    p.add_argument("--shape", default="cube4", help="a built-in shape (default %(default)s)")
    p.add_argument("--pieces", type=int, default=7, help="K (default %(default)s)")
    p.add_argument(
        "--time-limit", type=positive_float, default=60.0, help="seconds per job (default %(default)g)"
    )
    p.add_argument(
        "--max-jobs", type=int, default=0, help="the server's --max-jobs (default 0: two per core)"
    )
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=entry.cmd_bench_serve)


def _add_guide(bench: argparse._SubParsersAction) -> None:
    p = bench.add_parser(
        "guide", help="the solver against the same search guided by a guide network, and untrained"
    )
    p.add_argument(
        "--cells",
        default="cube5:13,sofa:19,desia-dog:60,mario:60",
        help="comma-separated SHAPE:K or SHAPE:K:path (a mesh: FILE@RESOLUTION:K)",
    )
    p.add_argument(
        "--guide", default="guide", help="a rllock train-guide run or checkpoint (default: shipped)"
    )
    p.add_argument(
        "--arms", default="solver,guided,untrained", help="solver, guided, untrained (comma-separated)"
    )
    p.add_argument("--seeds", default="0,1,2", help="comma-separated seeds (default 0,1,2)")
    p.add_argument("--time-limit", type=positive_float, default=60.0, help="seconds per arm and seed")
    p.add_argument(
        "--dives",
        type=int,
        default=None,
        help="the guided arms begin each restart from the best-valued of this many dives to the guide's "
        "horizon; 1: from the first, as the solver does (SearchConfig.dives; default: the search's own)",
    )
    p.add_argument(
        "--dive-share",
        type=float,
        default=None,
        help="the diving restarts' expansions at most this share of the solver's restarts' beside them; "
        "0 never dives (SearchConfig.dive_share; default: the search's own)",
    )
    p.add_argument(
        "--untrained-seed",
        type=int,
        default=0,
        help="the seed of the untrained arm's initial weights: other seeds show how far untrained "
        "networks differ among themselves (default 0)",
    )
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=entry.cmd_bench_guide)


def _add_checkers_and_solve(bench: argparse._SubParsersAction) -> None:
    p = bench.add_parser("checkers", help="raw chunks sampled and checked per second on one core")
    p.add_argument("--shape", default="cube6")
    p.add_argument("--pieces", type=int, default=25)
    p.add_argument("--piece", type=int, default=13, help="the piece being sampled (1-based)")
    p.add_argument("--removal", choices=REMOVAL_MODES, default="straight")
    p.add_argument("--seconds", type=positive_float, default=5.0)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=entry.cmd_bench_checkers)

    p = bench.add_parser("solve", help="the nine paper tasks: time per valid assembly vs the paper")
    p.add_argument("--tasks", help="subset, e.g. 5^3:13,6^3:20")
    add_protocol_args(p, count=5, time_limit=120.0, batch=False, per="task")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=entry.cmd_bench_solve)


def _add_selfplay(bench: argparse._SubParsersAction) -> None:
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
    p.set_defaults(func=entry.cmd_bench_selfplay)


def _add_scaling(bench: argparse._SubParsersAction) -> None:
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
    p.add_argument(
        "--features", help="the network's channels per level, as `train --features` (default 16,32,64)"
    )
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=entry.cmd_bench_scaling)


def _add_shapes(bench: argparse._SubParsersAction) -> None:
    p = bench.add_parser(
        "shapes", help="large shapes swept over K: time to the first valid assembly, solver and general"
    )
    p.add_argument(
        "--shapes",
        default=None,
        help="comma-separated shape names (default: desia-bunny, desia-dog, mario, bunny, spider)",
    )
    p.add_argument("--mesh", default=None, help="a mesh file (.stl, .obj, .ply, ...) at each --resolutions")
    p.add_argument("--resolutions", default="12,16,20", help="the mesh's resolutions")
    p.add_argument("--pieces", default=None, help="the K sweep (default 10,20,...,100; K > N skipped)")
    p.add_argument("--removal", choices=(*REMOVAL_MODES, "both"), default="straight")
    # Defaults sized for a first run on 2 cores (the solver's cells, a minute at most each); the full
    # sweep is --arms solver,general --time-limit 300.
    p.add_argument(
        "--arms", default="solver", help="solver, general, or both, comma-separated (default solver)"
    )
    p.add_argument(
        "--time-limit", type=positive_float, default=60.0, help="seconds per arm and task (default 60)"
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--workers",
        default="1",
        help="the solver's searches at once, comma-separated: one arm each, side by side (e.g. 1,2; "
        "default 1)",
    )
    p.add_argument(
        "--threads",
        default="1",
        help="one search's sampling threads, comma-separated: one arm each, beside the --workers arms "
        "(e.g. 1,2; default 1)",
    )
    p.add_argument("--batch", type=int, default=16, help="general's lockstep episodes per round")
    add_simulations_arg(p, " for general")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=entry.cmd_bench_shapes)


def _add_tables(bench: argparse._SubParsersAction) -> None:
    """The table benches, each under the paper's protocol per arm or run."""
    p = bench.add_parser(
        "paper", help="the paper's tasks: shipped checkpoints, untrained search and solver, beside the paper"
    )
    p.add_argument(
        "--tasks", default=None, help="comma-separated names, e.g. cube4-k9,sofa-k19 (default: all)"
    )
    add_table_bench_args(p, "arm")
    p.set_defaults(func=entry.cmd_bench_paper)

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
    p.set_defaults(func=entry.cmd_bench_ablation)

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
    p.set_defaults(func=entry.cmd_bench_transfer)


def _add_learning(bench: argparse._SubParsersAction) -> None:
    """A checkpoint against the same search untrained, and success rates over many episodes."""
    p = bench.add_parser("learning", help="a checkpoint against the same search with an untrained network")
    add_checkpoint_args(p)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=entry.cmd_bench_learning)

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
    add_protocol_args(p, count=None, time_limit=None)
    add_checkpoint_task_args(p)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=entry.cmd_bench_success)
