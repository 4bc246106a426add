"""`rllock bench learning` (a checkpoint against the same search untrained) and `rllock bench success`
(checkpoints' success rates over many episodes, with Wilson 95% intervals).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from typing import TypedDict

from orchestration.cli.common import (
    add_checkpoint_args,
    add_checkpoint_task_args,
    add_protocol_args,
    load_for,
)

log = logging.getLogger("rllock")


class ArmRow(TypedDict):
    """One arm of `rllock bench learning`, as its JSON document holds it."""

    valid: int
    episodes: int
    seconds: float
    success_rate: float
    time_per_valid_s: float | None


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


def add_commands(bench: argparse._SubParsersAction) -> None:
    p = bench.add_parser("learning", help="a checkpoint against the same search with an untrained network")
    add_checkpoint_args(p)
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
    add_protocol_args(p, count=None, time_limit=None)
    add_checkpoint_task_args(p)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_bench_success)
