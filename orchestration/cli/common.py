"""What several commands share: the protocol and task flags, checked output folders, checkpoint loading.

Each flag that more than one command takes is defined here once.
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path

from rllock.core.reference_checkers import REMOVAL_MODES
from rllock.errors import RLLockError


def positive_float(text: str) -> float:
    value = float(text)
    # nan compares false with everything, so `value <= 0` alone would let it (and inf) through.
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive finite number, got {text}")
    return value


def add_protocol_args(
    p: argparse.ArgumentParser,
    *,
    count: int | None,
    time_limit: float | None,
    batch: bool = True,
    seed: bool = True,
    per: str = "",
) -> None:
    """The paper's inference protocol, for every command that runs it: batches of --batch episodes until
    --count valid assemblies or --time-limit seconds (each `per` unit when given), from --seed. A None
    default leaves that flag out."""
    each = f" per {per}" if per else ""
    if count is not None:
        p.add_argument(
            "--count", type=int, default=count, help=f"valid assemblies to find{each} (default %(default)s)"
        )
    if batch:
        p.add_argument(
            "--batch",
            type=int,
            default=64,
            help="episodes per batch (one network call per simulation; default %(default)s)",
        )
    if time_limit is not None:
        p.add_argument(
            "--time-limit",
            type=positive_float,
            default=time_limit,
            help=f"seconds{each}, a hard limit (default %(default)g)",
        )
    if seed:
        p.add_argument("--seed", type=int, default=0, help="same seed, same results (default %(default)s)")


def add_task_args(p: argparse.ArgumentParser, pieces_help: str | None = None) -> None:
    """--shape, --resolution, --pieces, --removal and --seed; `pieces_help`: --pieces is optional, and
    this says what its absence does."""
    p.add_argument(
        "--shape",
        required=True,
        help="cube4 (any cubeN), box:WxHxD, ring, stairs, tube, a shipped shape by name (bunny, mario, ...), "
        "a .puz/.vol/.npy file, or a mesh: .stl, .obj, .ply, .off, .glb, .gltf or .3mf (holes capped, open "
        "surfaces filled, with a warning)",
    )
    p.add_argument(
        "--resolution",
        type=int,
        default=None,
        help="for mesh shapes: at most this many voxels along the longest side (default 8)",
    )
    if pieces_help is None:
        p.add_argument("--pieces", "-K", type=int, required=True, help="piece count K")
    else:
        p.add_argument("--pieces", "-K", type=int, default=None, help=f"piece count K ({pieces_help})")
    p.add_argument(
        "--removal",
        choices=REMOVAL_MODES,
        default="straight",
        help="straight: one axis slide per piece (default); path: DESIA's multi-move test",
    )
    p.add_argument("--seed", type=int, default=0, help="same seed, same results (default %(default)s)")


def assemblies_word(count: int) -> str:
    return "assembly" if count == 1 else "assemblies"


def fresh_out(path: str) -> Path:
    """The output folder, made now and checked writable before any work, so that nothing found is lost
    to a bad --out later; it must hold no earlier results (they would be overwritten or mixed up)."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise RLLockError(f"--out {out} is a file, not a folder")
    if out.is_dir() and any(out.glob("assembly_*")):
        raise RLLockError(f"--out {out} already holds results; choose another folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RLLockError(f"--out {out}: cannot make the folder ({exc.strerror or exc})") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise RLLockError(f"--out {out}: the folder is not writable")
    return out


def picture_writer():
    from rllock.files.render import write_picture  # matplotlib: loaded only where pictures are drawn

    return write_picture


def ray_on_loopback_unless(address: str | None) -> None:
    """A Ray instance started here serves this machine only: bind it to loopback, not to the host's
    outward address (Ray reads this setting when it is imported). A cluster run keeps Ray's default."""
    if not address:
        os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")


def add_simulations_arg(p: argparse.ArgumentParser, arms: str = "") -> None:
    p.add_argument(
        "--simulations",
        type=int,
        default=None,
        help=f"search simulations per decision{arms} (default: the checkpoint's own, as it was trained)",
    )


def add_checkpoint_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--checkpoint",
        required=True,
        help="a training run's log directory (its best checkpoint), one checkpoint directory, or the name "
        "of a shipped checkpoint (rllock pretrained)",
    )
    add_protocol_args(p, count=5, time_limit=3600.0)
    add_checkpoint_task_args(p)


def add_checkpoint_task_args(p: argparse.ArgumentParser) -> None:
    """The search budget and the task (`load_for`): a multi-task checkpoint's task, or a check on a
    single-task checkpoint's own."""
    add_simulations_arg(p)
    p.add_argument(
        "--shape",
        default=None,
        help="with --pieces: the task, for a multi-task checkpoint (general); for a single-task one, "
        "a check: fail unless the checkpoint is for this shape",
    )
    p.add_argument(
        "--pieces",
        type=int,
        default=None,
        help="K, with --shape: the task for a multi-task checkpoint, a check for a single-task one",
    )
    p.add_argument(
        "--removal",
        choices=REMOVAL_MODES,
        default=None,
        help="optional: fail unless the checkpoint uses this removal mode",
    )
    p.add_argument("--resolution", type=int, default=None, help="for a mesh --shape: as given to train")


def named_task(args: argparse.Namespace):
    """The task named by --shape, --pieces, --removal and --resolution (`rllock.search.serving.Named`)."""
    from rllock.search.serving import Named

    return Named(args.shape, args.pieces, args.removal, args.resolution)


def load_for(args: argparse.Namespace):
    """The policy for `generate`, `bench learning` and `bench success`: the checkpoint's task for the one
    named on the command line (`rllock.search.serving.served`), searching with --simulations when
    given."""
    from rllock.search.inference import load_policy, with_simulations

    if args.batch < 1:
        raise RLLockError(f"--batch must be at least 1, got {args.batch}")
    return with_simulations(load_policy(args.checkpoint, named_task(args)), args.simulations)
