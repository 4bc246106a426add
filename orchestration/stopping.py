"""A training run's stop on a signal: Ctrl-C (SIGINT) and SIGTERM (`kill`, `ray job stop`, a scheduler)
ask the run to stop after a final checkpoint; a second signal aborts at once. The actor-learner loop
(`rllock.orchestration.loop`) polls it for both trainers."""

from __future__ import annotations

import logging
import signal
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

log = logging.getLogger(__name__)

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class StopRequest:
    """Whether a stop was asked for and by which signal; a run polls `requested` between its steps."""

    def __init__(self) -> None:
        self.signum: int | None = None

    @property
    def requested(self) -> bool:
        return self.signum is not None

    def handle(self, signum: int, frame: FrameType | None) -> None:
        del frame
        if self.requested:
            raise KeyboardInterrupt
        self.signum = signum
        log.warning("%s: saving a checkpoint and stopping (again to abort)", signal_name(signum))


def signal_name(signum: int | None) -> str:
    return "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum or signal.SIGTERM).name


def exit_status(signum: int | None) -> int:
    """The exit status of a run stopped by `signum` (None: Ctrl-C), as a shell reports a process killed
    by it: 130 after Ctrl-C, 143 after SIGTERM."""
    return 128 + int(signum or signal.SIGINT)


@contextmanager
def stop_on_signals(request: StopRequest) -> Iterator[None]:
    """`request` handles SIGINT and SIGTERM within the block; the handlers before it are put back after."""
    previous = {s: signal.signal(s, request.handle) for s in SIGNALS}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
