"""The trainers' stop on a signal (`rllock.orchestration.stopping`), with real signals to this process."""

from __future__ import annotations

import functools
import os
import signal
import subprocess

import pytest

from rllock.orchestration.stopping import StopRequest, exit_status, signal_name, stop_on_signals


def test_a_first_signal_asks_for_a_stop_a_second_aborts_and_the_handlers_come_back():
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    request = StopRequest()
    with stop_on_signals(request):
        assert not request.requested
        os.kill(os.getpid(), signal.SIGTERM)
        assert request.requested and request.signum == signal.SIGTERM
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)
        assert request.signum == signal.SIGTERM  # the first signal is the one that stopped the run
    assert {s: signal.getsignal(s) for s in before} == before
    ctrl_c = StopRequest()
    with pytest.raises(RuntimeError), stop_on_signals(ctrl_c):
        os.kill(os.getpid(), signal.SIGINT)
        raise RuntimeError  # the handlers come back when the run fails too
    assert ctrl_c.signum == signal.SIGINT and {s: signal.getsignal(s) for s in before} == before


def test_signal_names_are_what_a_user_pressed_or_sent():
    assert signal_name(signal.SIGINT) == "Ctrl-C" and signal_name(signal.SIGTERM) == "SIGTERM"


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_stopped_runs_exit_status_is_the_shells_for_its_signal(signum):
    # What the shell reports for a process the signal killed, the status scripts and schedulers test.
    shell = f"sh -c 'kill -{int(signum)} $$'; echo $?"
    # From the signal's default: a suite started in the background (`cmd &` in a script) inherits SIGINT
    # ignored, which no shell can undo, and the inner shell would then live on and report 0.
    default = functools.partial(signal.signal, signum, signal.SIG_DFL)
    killed = subprocess.run(
        ["sh", "-c", shell], capture_output=True, text=True, check=True, preexec_fn=default
    )
    assert exit_status(signum) == int(killed.stdout) and exit_status(None) == exit_status(signal.SIGINT)
