"""Where a shipped file came from, naming nothing of the machine that wrote it: the command, commit,
machine and date of a training session (`provenance`), and paths made `portable`."""

from __future__ import annotations

import datetime
import os
import platform
import re
import subprocess
import sys
from pathlib import Path

import jax

# An absolute path inside a command line: at its start, after a space or after `--flag=`.
_ABSOLUTE_IN_COMMAND = re.compile(r"(?<![^\s=])/[^\s]*")
# The folder that holds the `rllock` package: the repository, or site-packages.
_PACKAGE_ROOT = Path(__file__).resolve().parents[2]


def _commit() -> str | None:
    """The git commit of this source tree (with "-dirty" when it has changes), or None outside git."""
    root = Path(__file__).resolve().parents[2]
    # close_fds=False lets subprocess use posix_spawn: no fork in a process where JAX runs threads.
    try:
        head = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            timeout=10,
            close_fds=False,
        )
        dirty = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=10,
            close_fds=False,
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    if head.returncode != 0:
        return None
    return head.stdout.strip() + ("-dirty" if dirty.stdout.strip() else "")


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def portable(path: str | Path, tail: int | None = None) -> str:
    """`path` as a shipped file records it, naming nothing of the machine that wrote it. A relative
    path stays as it is. An absolute one becomes relative to the current directory when it lies
    under it (`runs/cube4-k9/best/5703` from the directory that holds `runs/`); else relative to the
    folder that holds the `rllock` package when under that (`rllock/checkpoints/cube4-k9`); else its
    last `tail` parts, by default the run's folder and the rest below it: from the folder above
    `best/` or `checkpoints/` (`/data/runs/cube4-k9/best/5703` gives `cube4-k9/best/5703`), or the
    last part alone where there is no such folder (a run's log directory, `/tmp/cube6-k22` gives
    `cube6-k22`)."""
    path = Path(path)
    if not path.is_absolute():
        return str(path)
    for candidate in (path, path.resolve()):
        for base in (Path.cwd(), Path.cwd().resolve(), _PACKAGE_ROOT):
            if candidate.is_relative_to(base) and base != Path(base.anchor):
                return str(candidate.relative_to(base))
    parts = path.parts[1:]
    if tail is None:
        tail = 1
        for i in range(len(parts) - 1, 0, -1):
            if parts[i] in ("best", "checkpoints"):
                tail = len(parts) - i + 1
                break
    return str(Path(*parts[-tail:])) if parts else "."


def portable_command(command: str) -> str:
    """A command line with every absolute path in it made `portable`."""
    return _ABSOLUTE_IN_COMMAND.sub(lambda m: portable(m.group()), command)


def portable_sessions(sessions) -> list[dict]:
    """Training sessions (`provenance`) with the absolute paths in their command lines made `portable`."""
    return [
        {**s, "command": portable_command(s["command"])} if isinstance(s.get("command"), str) else s
        for s in sessions
    ]


def provenance() -> dict:
    """What made a checkpoint, for the record: command, commit, machine and date."""
    device = jax.devices()[0]
    return {
        "command": portable_command(" ".join(["rllock", *sys.argv[1:]])),
        "commit": _commit(),
        "machine": f"{os.cpu_count()} x {_cpu_model()}, {device.platform} ({device.device_kind})",
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }
