"""The `rllock` command line: the parser, logging, and one-line errors. Bad input ends in one line on
stderr and exit status 2; Ctrl-C in exit status 130. Each command group registers its own subcommands.
"""

from __future__ import annotations

import argparse
import gc
import logging
import os
import sys

from rllock.errors import RLLockError
from rllock.orchestration.bench import commands as bench_commands
from rllock.orchestration.cli import assemblies, service, training
from rllock.process import setup_jax_cache


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rllock", description="Interlocking assemblies from voxel shapes.")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)
    for group in (assemblies, training, service, bench_commands):
        group.add_commands(sub)
    return parser


def reference() -> str:
    """docs/cli.md: every command's and subcommand's --help, from the parser itself, so the reference
    cannot drift from the flags (a test compares the file; `bash scripts/cli_reference.sh` rewrites it).
    Wrapped at a fixed width, whatever the terminal."""
    parts = [
        "# `rllock` command reference\n",
        "Every command's `--help`, generated from the parser by `bash scripts/cli_reference.sh`; "
        "do not edit by hand.\n",
    ]

    def walk(parser: argparse.ArgumentParser, depth: int) -> None:
        parser.formatter_class = lambda prog: argparse.HelpFormatter(prog, width=100)
        parts.append(f"{'#' * depth} `{parser.prog}`\n\n```text\n{parser.format_help()}```\n")
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub in dict.fromkeys(action.choices.values()):  # aliases map to the same parser
                    walk(sub, min(depth + 1, 4))

    walk(build_parser(), 2)
    return "\n".join(parts)


def entry(argv: list[str] | None = None) -> int:
    """The `rllock` command as its process runs it (the console script, `python -m`): `main`, then
    the objects left are frozen out of the garbage collector. Its last pass over them (the libraries'
    millions) would lengthen every command on its way out, for memory the process gives back anyway."""
    try:
        return main(argv)
    finally:
        gc.freeze()


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
    setup_jax_cache()  # compiled programs kept across processes, per user ($RLLOCK_JAX_CACHE)
    try:
        if getattr(args, "count", 1) < 1:
            raise RLLockError(f"--count must be at least 1, got {args.count}")
        return args.func(args)
    except RLLockError as exc:
        sys.stderr.write(f"rllock: error: {exc}\n")
        return 2
    except OSError as exc:  # unwritable or missing output paths, full disks: the system's own words
        logging.getLogger("rllock").debug("where it happened", exc_info=True)  # with --verbose
        sys.stderr.write(f"rllock: error: {exc.strerror or exc}: {exc.filename or ''}\n")
        return 2
    except KeyboardInterrupt:
        sys.stderr.write("rllock: interrupted\n")
        return 130


if __name__ == "__main__":
    sys.exit(main())
