"""The training commands: `train` (self-play on Ray), `train-guide` (the guide network of `solve
--guide`), `generate` (assemblies from a checkpoint) and `pretrained` (the checkpoints shipped by name).

`add_commands(subparsers)` adds them to the `rllock` parser; each handler takes the parsed arguments,
raises RLLockError on bad input and returns the exit status.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from rllock.config import EVALUATION_MODES, METHODS, TrainConfig, with_method_defaults
from rllock.core.reference_checkers import REMOVAL_MODES
from rllock.errors import RLLockError
from rllock.orchestration.cli.common import (
    add_checkpoint_args,
    assemblies_word,
    fresh_out,
    load_for,
    picture_writer,
    ray_on_loopback_unless,
)
from rllock.orchestration.cli.flags import add_flags, from_flags, given_flags
from rllock.orchestration.cli.longwork import INTERRUPTED, advice, graceful_stop, is_interrupt, kept
from rllock.orchestration.stopping import exit_status


def train_config(args: argparse.Namespace) -> TrainConfig:
    """The run's config from `rllock train`'s flags, with the method's own settings for the flags not
    given (METHOD_DEFAULTS), checked."""
    config = with_method_defaults(from_flags(TrainConfig, args), given_flags(args))
    config.validate()
    return config


def cmd_train(args: argparse.Namespace) -> int:
    if args.resume:
        from rllock.files.checkpoint import run_config

        config = run_config(Path(args.resume), minutes=args.minutes, max_learner_steps=args.max_learner_steps)
    else:
        config = train_config(args)
    ray_on_loopback_unless(config.address)
    from rllock.orchestration.train import train

    result = train(config, resume=bool(args.resume))
    if result.interrupted:
        sys.stdout.write(
            f"train: stopped at learner step {result.steps}; resume with: "
            f"rllock train --resume {result.logdir}\n"
        )
        return exit_status(result.stop_signal)
    val, best = result.validation, result.best_success_rate
    last = "none (it did not fit the budget)" if val is None else f"{100 * val.success_rate:.1f}% valid"
    sys.stdout.write(
        f"train: {result.steps} learner steps, {result.episodes} self-play episodes "
        f"({result.episodes_per_sec:.2f}/s, {result.simulations_per_sec:.0f} simulations/s) in "
        f"{result.seconds:.0f} s; last validation {last}, best "
        f"{'none yet' if best < 0 else f'{100 * best:.1f}%'}\n"
        f"checkpoints: {result.logdir}/best (best validated) and {result.logdir}/checkpoints (latest), "
        f"TensorBoard events beside them\n"
    )
    return 0


def cmd_generate(args: argparse.Namespace) -> int:
    from rllock.core.feasibility import check_feasible

    if args.actors < 0:
        raise RLLockError(f"--actors must be >= 0, got {args.actors}")
    if args.address and not args.actors:
        raise RLLockError("--address needs --actors N: generation joins a Ray cluster only with actors")
    with _ray_first(args):
        policy = load_for(args)
        check_feasible(policy.task)
        out = fresh_out(args.out)
        try:
            with graceful_stop() as stop:
                result = _generate_into(args, policy, out, stop)
        except (KeyboardInterrupt, SystemError) as exc:
            if not is_interrupt(exc):
                raise
            sys.stdout.write(kept("generate", len(list(out.glob("assembly_*"))), out))
            return INTERRUPTED
    if stop():
        sys.stdout.write(kept("generate", result.valid, out))
        return INTERRUPTED
    sys.stdout.write(_generate_summary(args, policy.task, result))
    return 0 if result.valid else 1


@contextmanager
def _ray_first(args: argparse.Namespace) -> Iterator[None]:
    """With --actors, Ray for the rounds, started before anything else: it starts its processes with
    fork(), which must come before JAX starts its threads (with the policy's arrays)."""
    if not args.actors:
        yield
        return
    ray_on_loopback_unless(args.address)
    import ray

    from rllock.orchestration.pool import start_ray

    started = start_ray(args.address)
    try:
        yield
    finally:
        if started:
            ray.shutdown()


def _generate_summary(args: argparse.Namespace, task, result) -> str:
    if result.valid == 0:
        more = f"more time (--time-limit {2 * args.time_limit:g}) or more simulations (--simulations)"
        return (
            f"generate: no valid assembly of {task.shape_name} K={task.pieces} in {result.episodes} "
            f"episodes ({result.seconds:.1f} s)\n"
            f"  best: {result.best_placed} of {task.pieces - 1} pieces placed\n"
            f"  {advice(task, fits_general=False, more=more)}\n"
        )
    return (
        f"generate: {result.valid} valid {assemblies_word(result.valid)} of {task.shape_name} "
        f"K={task.pieces} from {result.episodes} episodes in {result.seconds:.1f} s: "
        f"{result.time_per_valid_s:.2f} s per valid assembly -> {args.out}\n"
    )


def _generate_into(args: argparse.Namespace, policy, out: Path, stop):
    """The protocol's rounds, in this process or on --actors Ray actors, written into `out`."""
    settings = dict(
        count=args.count,
        batch=args.batch,
        time_limit=args.time_limit,
        seed=args.seed,
        out=out,
        picture=picture_writer(),
    )
    if args.actors:
        from rllock.orchestration.generate import generate_on_ray

        return generate_on_ray(policy, actors=args.actors, address=args.address, stop=stop, **settings)
    from rllock.search.inference import generate

    return generate(policy, stop=stop, **settings)


def cmd_pretrained(args: argparse.Namespace) -> int:
    from rllock.files.checkpoint import shipped_names
    from rllock.search import guide_checkpoint as guides
    from rllock.search import pretrained

    if args.ship is not None:
        if args.name is None:
            raise RLLockError("--ship needs --name, the name to ship the checkpoint under (e.g. cube4-k9)")
        if guides.is_guide_run(Path(args.ship)):
            target = guides.ship_guide(Path(args.ship), args.name)
        else:
            target = pretrained.ship(Path(args.ship), args.name)
        size = sum(f.stat().st_size for f in target.rglob("*") if f.is_file())
        sys.stdout.write(f"shipped {args.name}: {target} ({size / 2**20:.1f} MiB)\n")
        return 0
    rows = [pretrained.describe(name) for name in shipped_names()]
    guide_rows = [guides.describe_guide(name) for name in guides.shipped_guides()]
    if args.json:
        sys.stdout.write(json.dumps(rows + [{"kind": "guide", **g} for g in guide_rows]) + "\n")
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
    if guide_rows:
        lines += ["", "Guide networks (rllock solve --guide NAME; --guide alone: guide):", ""]
        lines += guide_table(guide_rows)
    sys.stdout.write("\n".join(lines) + "\n")
    return 0


def guide_table(rows: list[dict]) -> list[str]:
    """The shipped guides with what made them: a run's searches, or other runs' snapshots."""
    from rllock.search import pretrained

    lines = [
        "| name | window | trained on | learner steps | machine | date | commit | command |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for g in rows:
        data = (
            f"{sum(r['states'] for r in g['replay']):,} states kept from {len(g['replay'])} run(s)"
            if g["replay"]
            else f"{g['searches']} searches"
        )
        lines.append(
            f"| {g['name']} | {g['window']} | {data} | {g['learner_steps']} | "
            f"{pretrained.machine_summary(g['machine'])} | {(g['date'] or '-')[:10]} | "
            f"{(g['commit'] or '-')[:12]} | `{g['command']}` |"
        )
    return lines


def cmd_train_guide(args: argparse.Namespace) -> int:
    from rllock.config import GuideTrainConfig

    if args.resume:
        from rllock.orchestration.guide_train import resume_config

        config = resume_config(
            Path(args.resume), args.minutes, args.actors, args.address, args.max_learner_steps
        )
    else:
        config = from_flags(GuideTrainConfig, args)
    config.validate()
    ray_on_loopback_unless(config.address)
    from rllock.orchestration.guide_train import train_guide

    result = train_guide(config, resume=bool(args.resume))
    if result.interrupted:
        sys.stdout.write(f"train-guide: stopped; resume with: rllock train-guide --resume {result.logdir}\n")
        return exit_status(result.stop_signal)
    done = (
        f"on the states of {config.replay_from}"
        if config.replay_from
        else f"{result.searches} searches ({result.solved} solved)"
    )
    sys.stdout.write(
        f"train-guide: {result.steps} learner steps, {done} in {result.seconds:.0f} s; checkpoints: "
        f"{result.logdir}/checkpoints; use: rllock solve ... --guide {result.logdir}\n"
    )
    return 0


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    from rllock.config import GUIDE_LABELS, GuideTrainConfig

    p = subparsers.add_parser(
        "train-guide",
        help="train the guide network of rllock solve --guide on Ray (a curriculum of searches)",
    )
    add_flags(p, GuideTrainConfig, choices={"label": GUIDE_LABELS})
    p.add_argument(
        "--resume",
        metavar="LOGDIR",
        default=None,
        help="continue the guide run in LOGDIR with its saved config; --minutes to add, --max-learner-steps "
        "a new step limit, and --actors and --address say where it goes on",
    )
    p.set_defaults(func=cmd_train_guide)

    p = subparsers.add_parser("train", help="self-play training on Ray (local, or a cluster with --address)")
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

    p = subparsers.add_parser("generate", help="assemblies from a trained checkpoint (batched MCTS)")
    add_checkpoint_args(p)
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

    p = subparsers.add_parser("pretrained", help="the trained checkpoints shipped with RL-Lock, by name")
    p.add_argument("--json", action="store_true", help="print one JSON list")
    p.add_argument(
        "--ship",
        metavar="LOGDIR",
        default=None,
        help="for maintainers: copy the best checkpoint of this run into the package (parameters only)",
    )
    p.add_argument("--name", default=None, help="with --ship: the name, e.g. cube4-k9")
    p.set_defaults(func=cmd_pretrained)
