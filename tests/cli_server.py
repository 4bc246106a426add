"""The `rllock` command for the tests, its imports paid once: a process that imports the command and the
libraries it loads (seconds on a busy machine, longer than most bad-input checks take), then for
each request forks a child that is the command, `python -m rllock.orchestration.cli ARGS` from the import on:
its own process, its own stdin (empty), stdout and stderr (files), working folder and exit status, and
an uncaught exception ends it with a traceback and status 1, as the interpreter does. `tests/helpers.py`
(`run_cli`) starts one per pytest worker.

Requests on stdin, one JSON line each: {"args", "cwd", "out", "err", "timeout"}; the reply on stdout,
one JSON line: {"code"}, the exit status as `subprocess` gives it (minus the signal for a killed child),
or {"timeout": true} when the child ran past its timeout and was killed.
"""

from __future__ import annotations

import importlib.util
import json
import os
import signal
import sys
import time


def _child(request: dict) -> None:
    """Become the command: never returns (`sys.exit` ends this forked process as the command would)."""
    # Descriptors 0-2 only, as a fresh interpreter has: each file is opened, moved there and closed.
    for fd, path, flags in (
        (0, os.devnull, os.O_RDONLY),
        (1, request["out"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC),
        (2, request["err"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC),
    ):
        opened = os.open(path, flags, 0o600)
        os.dup2(opened, fd)
        os.close(opened)
    # The server's stdin buffer holds the next requests, not the command's input.
    sys.stdin = open(0, closefd=False)
    os.chdir(request["cwd"])
    from rllock.orchestration.cli.main import entry

    sys.argv = [request["entry"], *request["args"]]
    sys.exit(entry(request["args"]))


def _wait(pid: int, timeout: float) -> dict:
    deadline = time.monotonic() + timeout
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            return {"code": os.waitstatus_to_exitcode(status)}
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            return {"timeout": True}
        time.sleep(0.005)


def serve() -> None:
    import flax.linen  # noqa: F401
    import jax  # noqa: F401
    import optax  # noqa: F401
    import orbax.checkpoint  # noqa: F401

    import rllock.orchestration.cli.main  # noqa: F401

    # What `python -m rllock.orchestration.cli` puts in sys.argv[0] (found, not imported: importing it runs
    # it).
    entry = importlib.util.find_spec("rllock.orchestration.cli.__main__").origin  # type: ignore[union-attr]
    reply = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)  # a library's stray print must not end up in the replies
    print("ready", file=reply, flush=True)
    for line in sys.stdin:
        request = json.loads(line) | {"entry": entry}
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:
            reply.close()
            _child(request)
        print(json.dumps(_wait(pid, request["timeout"])), file=reply, flush=True)


if __name__ == "__main__":
    serve()
