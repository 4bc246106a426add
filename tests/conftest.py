from __future__ import annotations

import os
from pathlib import Path

import pytest

# Every Ray instance in the tests is one machine: keep its processes on loopback (Ray otherwise binds
# this host's outward address). Read by Ray at import time, so set before any test imports it.
os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"


@pytest.fixture(scope="session")
def data() -> Path:
    """The data vendored in the package (`rllock/data/`: published/ assemblies, shapes/)."""
    from rllock.core.shapes import data_path

    return data_path("")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Under xdist (`scripts/test.sh` runs two workers), the tests that start Ray run one after another
    on one worker: two Ray instances at once would fight over the machine's cores and make their timing
    tests flaky, while the other tests fill the other worker."""
    for item in items:
        if item.get_closest_marker("ray"):
            item.add_marker(pytest.mark.xdist_group("ray"))
