from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

# Every Ray instance in the tests is one machine: keep its processes on loopback (Ray otherwise binds
# this host's outward address). Read by Ray at import time, so set before any test imports it.
os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"


def pytest_configure(config: pytest.Config) -> None:
    """JAX's persistent compilation cache in every test process too, as the `rllock` command sets it up
    (`rllock.process.setup_jax_cache`): a program one process compiled, the others read back."""
    from rllock.process import setup_jax_cache

    setup_jax_cache()


@pytest.fixture(scope="session")
def data() -> Path:
    """The data vendored in the package (`rllock/data/`: published/ assemblies, shapes/)."""
    from rllock.core.shapes import data_path

    return data_path("")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Under xdist (`scripts/test.sh` runs two workers), the tests that start Ray run one after another
    on one worker: two Ray instances at once would fight over the machine's cores and make their timing
    tests flaky, while the other tests fill the other worker. A module may name a group of its own
    (`RAY_GROUP`): the service's tests, which start one Ray instance for the whole module and make
    no timing claims, go to whichever worker is free. xdist's loadgroup reads a group from the test
    id's "@group" suffix, which xdist 3.8 writes where pytest 9 no longer keeps the id (`_nodeid`, not
    `_id`): the suffix is set here."""
    from _pytest.nodeid import coerce_node_id

    if not getattr(config.option, "loadgroup", False):
        return
    for item in items:
        if item.get_closest_marker("ray") and "@" not in item.nodeid:
            group = getattr(getattr(item, "module", None), "RAY_GROUP", "ray")
            item._id = coerce_node_id(f"{item.nodeid}@{group}")  # type: ignore[attr-defined]


@pytest.fixture
def cluster(monkeypatch) -> Iterator[tuple]:
    """(the Cluster, the Jobs API's address, a function that adds a worker node of one CPU), torn down
    whatever the test does. Each worker node has a temporary folder of its own, as separate machines
    would: nodes that share one delete each other's unpacked job folders (Ray keeps them per node)."""
    monkeypatch.setenv("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
    # `ray job stop` sends SIGTERM, then SIGKILL after this many seconds (Ray's default: 3).
    monkeypatch.setenv("RAY_JOB_STOP_WAIT_TIME_S", "60")
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    from ray.cluster_utils import Cluster

    from rllock.orchestration.bench.serve import free_port

    port = free_port()
    head = {
        "num_cpus": 0,
        "node_ip_address": "127.0.0.1",
        "include_dashboard": True,
        "dashboard_host": "127.0.0.1",
        "dashboard_port": port,
        # Not Ray's fixed default (52365), which a Ray instance of another test (the service's) may hold:
        # the head's job agent then never starts ("No available agent to submit job", 180 s).
        "dashboard_agent_listen_port": free_port(),
        # The head declares a silent node dead after 3 missed health checks a second apart, not Ray's
        # default 5 of 3 s each: the same path, in a test-sized time.
        "_system_config": {"health_check_period_ms": 1000, "health_check_failure_threshold": 3},
    }
    folders: list[str] = []

    def add_worker():
        # Ray's socket paths must stay under 108 bytes: pytest's tmp_path is too deep for them.
        folders.append(tempfile.mkdtemp(prefix="rlw", dir="/tmp"))
        return created.add_node(num_cpus=1, node_ip_address="127.0.0.1", temp_dir=folders[-1])

    created = Cluster(initialize_head=True, head_node_args=head)
    try:
        yield created, f"http://127.0.0.1:{port}", add_worker
    finally:
        created.shutdown()
        for folder in folders:
            shutil.rmtree(folder, ignore_errors=True)
