"""What the long commands (`solve`, `generate`) tell the user while and after they work: a progress bar,
a clean stop on Ctrl-C, and, when nothing was found, what the search reached and what to try."""

from __future__ import annotations

import logging
import signal
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import replace

from rllock.core.env import Task

log = logging.getLogger("rllock")

# The exit status of a command stopped by Ctrl-C, as shells report a process ended by SIGINT.
INTERRUPTED = 130


@contextmanager
def graceful_stop() -> Iterator[Callable[[], bool]]:
    """Inside: the first Ctrl-C asks the work to stop at its next check (what it has written is kept and
    complete); a second one stops it at once. Yields `stop()`, true once asked."""
    asked = False

    def on_sigint(signum, frame) -> None:
        nonlocal asked
        if asked:
            raise KeyboardInterrupt
        asked = True
        log.warning("stopping (Ctrl-C again to stop at once)")

    previous = signal.signal(signal.SIGINT, on_sigint)
    try:
        yield lambda: asked
    finally:
        signal.signal(signal.SIGINT, previous)


def is_interrupt(exc: BaseException) -> bool:
    """A Ctrl-C, also when it arrived inside compiled code: numba then reports a SystemError whose
    context is the KeyboardInterrupt."""
    return isinstance(exc, KeyboardInterrupt) or (
        isinstance(exc, SystemError) and isinstance(exc.__context__, KeyboardInterrupt)
    )


def kept(command: str, count: int, where: object) -> str:
    """The line a stopped command ends with: what it kept and where."""
    what = "no assembly" if count == 0 else f"{count} valid {'assembly' if count == 1 else 'assemblies'}"
    return f"{command}: interrupted; kept {what}" + (f" in {where}" if count else "") + "\n"


def general_serves(task: Task) -> bool:
    """Whether the shipped multi-task checkpoint `general` can generate for `task` (the check
    `generate --checkpoint general` makes: a canvas it plays on, its removal mode and checkers)."""
    from rllock.files.checkpoint import SHIPPED, read_metadata, shipped_names
    from rllock.search.serving import serves

    return "general" in shipped_names() and serves(
        read_metadata(SHIPPED / "general"), SHIPPED / "general", task
    )


def advice(task: Task, *, fits_general: bool, more: str) -> str:
    """What to try after a search found nothing: `more` names the budget that can grow."""
    others = [
        _sizes(replace(task, pieces=k)) for k in (task.pieces - 1, task.pieces + 1) if 2 <= k <= task.size
    ]
    tries = [more, f"another K, {' or '.join(others)}: a last piece well over the others is easier"]
    if task.removal == "straight":
        tries.append("--removal path (a weaker test: pieces may leave by several moves)")
    if fits_general:
        tries.append(f"rllock generate --checkpoint general --shape {task.shape_name} --pieces {task.pieces}")
    return "try " + "; ".join(tries)


def _sizes(task: Task) -> str:
    """K with the sizes it gives: one K more or fewer can change the pieces' size and move the last
    piece's by many voxels (desia-bunny: K=80 has a last piece of 18, K=81 of 86)."""
    return f"K={task.pieces} (pieces of {task.piece_size}, the last {task.last_size})"
