from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

# Every Ray instance in the tests is one machine: keep its processes on loopback (Ray otherwise binds
# this host's outward address). Read by Ray at import time, so set before any test imports it.
os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"


@pytest.fixture(scope="session")
def data() -> Path:
    """The data vendored in the package (`rllock/data/`: published/ assemblies, shapes/)."""
    from rllock.shapes import data_path

    return data_path("")


def run_cli(*args: str, timeout: float = 300):
    """Run the installed `rllock` command in a subprocess: (exit code, stdout, stderr)."""
    import subprocess

    proc = subprocess.run(
        [sys.executable, "-m", "rllock.cli", *args], capture_output=True, text=True, timeout=timeout
    )
    return proc.returncode, proc.stdout, proc.stderr
