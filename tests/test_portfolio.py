"""`solve --workers N`: N searches from different seeds in N processes (`rllock.search.portfolio`)."""

from __future__ import annotations

import json
import multiprocessing as mp
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from helpers import actor_nodes, run_cli

from rllock.core.env import make_task
from rllock.core.verifier import verify_labels
from rllock.files.assembly import read_assembly
from rllock.search import solver
from rllock.search.portfolio import portfolio_search, worker_seed
from rllock.search.solver import SamplingPool, SearchStats, search


def test_workers_find_distinct_verified_assemblies_each_found_again_by_its_seed():
    task = make_task("cube4", 7)
    found = []
    for f in portfolio_search(task, seed=0, workers=2, time_limit=120):
        found.append(f)
        if len(found) == 4:
            break
    assert len({f.labels.tobytes() for f in found}) == 4
    assert all(verify_labels(f.labels, task.removal).valid for f in found)
    seeds = {worker_seed(0, 0), worker_seed(0, 1)}
    assert worker_seed(0, 0) == 0 and len(seeds) == 2 and {f.seed for f in found} <= seeds
    for f in found:  # a worker runs the plain search: its seed alone finds the assembly again
        again = [g.labels for g, _ in zip(search(task, seed=f.seed, time_limit=60), range(4))]
        assert any(np.array_equal(f.labels, a) for a in again)
    assert not mp.active_children()  # leaving the loop stopped every worker


def test_workers_stop_at_the_time_limit_with_their_progress_summed():
    task = make_task("desia-bunny", 80)  # none in a few seconds
    stats, reports = SearchStats(), []
    started = time.monotonic()
    found = list(
        portfolio_search(task, seed=0, workers=2, time_limit=4, stats=stats, report=reports.append, threads=2)
    )
    elapsed = time.monotonic() - started
    assert not found and 4 <= elapsed < 7, elapsed
    assert reports and stats.expansions > 0 and stats.restarts >= 2 and 0 < stats.placed < 79
    assert not mp.active_children()
    assert not [t for t in threading.enumerate() if t.name.startswith("rllock-lookahead")]


@pytest.mark.parametrize(
    "shape, pieces, removal",
    [("cube4", 7, "straight"), ("cube5", 13, "path"), ("desia-bunny", 40, "straight")],  # the last: deep mode
)
def test_the_lookahead_on_threads_is_the_same_search_node_for_node(shape, pieces, removal, monkeypatch):
    task = make_task(shape, pieces, removal)
    monkeypatch.setattr(solver, "THREADED_FROM_SECONDS", 0.0)  # threads from the first node, however fast
    sampled_on: set[str] = set()
    sample = solver.sample_accepted

    def watched(*args, **kwargs):
        sampled_on.add(threading.current_thread().name)
        return sample(*args, **kwargs)

    monkeypatch.setattr(solver, "sample_accepted", watched)
    runs = []
    for threads in (1, 3):
        stats = SearchStats()
        found = [
            f.labels
            for f, _ in zip(search(task, seed=3, time_limit=60, stats=stats, threads=threads), range(2))
        ]
        runs.append((found, stats.expansions, stats.restarts))
    (plain, expansions, restarts), (threaded, t_expansions, t_restarts) = runs
    assert any(name.startswith("rllock-lookahead") for name in sampled_on)
    assert len(plain) == 2 and (t_expansions, t_restarts) == (expansions, restarts)
    assert all(np.array_equal(a, b) for a, b in zip(plain, threaded, strict=True))


def test_threads_are_used_only_once_samples_are_long_enough_to_share():
    pool = SamplingPool(ThreadPoolExecutor(2))
    try:
        assert not pool.worth_it(8)  # nothing measured yet
        pool.took(1e-4)
        assert not pool.worth_it(8)
        for _ in range(20):
            pool.took(2e-3)
        assert pool.worth_it(8) and not pool.worth_it(1)
    finally:
        pool.executor.shutdown()


def test_solve_with_workers_writes_verified_assemblies_that_name_their_seed(tmp_path):
    out = tmp_path / "o"
    code, stdout, err = run_cli(
        "solve", "--shape", "cube4", "--pieces", "7", "--count", "3", "--workers", "2", "--out", str(out)
    )
    assert code == 0 and "solve: 3 valid assemblies" in stdout, err
    for folder in sorted(out.glob("assembly_*")):
        labels, meta = read_assembly(folder)
        assert verify_labels(labels).valid
        method = json.loads((folder / "assembly.json").read_text())["method"]
        assert method["workers"] == 2 and meta["seed"] in {worker_seed(0, 0), worker_seed(0, 1)}
    code, _, err = run_cli("solve", "--shape", "cube4", "--pieces", "7", "--workers", "0", "--out", str(out))
    assert code == 2 and err.strip() == "rllock: error: --workers must be at least 1, got 0"
    code, _, err = run_cli("solve", "--shape", "cube4", "--pieces", "7", "--threads", "0", "--out", str(out))
    assert code == 2 and err.strip() == "rllock: error: --threads must be at least 1, got 0"
    code, _, err = run_cli(
        "solve",
        "--shape",
        "cube4",
        "--pieces",
        "7",
        "--threads",
        "2",
        "--address",
        "127.0.0.1:9",
        "--out",
        str(out),
    )
    assert code == 2 and err.strip().startswith("rllock: error: --threads is for a search on this machine")


@pytest.mark.slow
@pytest.mark.ray
def test_solve_on_a_ray_cluster_runs_one_worker_on_each_node(cluster, tmp_path):
    """`solve --address`: the workers are Ray actors on a real cluster of two one-CPU worker nodes (and a
    head with none) on 127.0.0.1; each node runs one, the assemblies are verified and written, and no
    worker is left alive."""
    created, api, add_worker = cluster
    nodes = {add_worker().node_id for _ in range(2)}
    created.wait_for_nodes()
    out = tmp_path / "o"
    code, stdout, err = run_cli(
        "solve", "--shape", "cube4", "--pieces", "7", "--count", "2", "--workers", "2",
        "--address", created.address, "--out", str(out),
    )  # fmt: skip
    assert code == 0 and "solve: 2 valid assemblies" in stdout, err
    line = next(x for x in err.splitlines() if "search workers on" in x)
    assert "on 2 Ray node(s)" in line and all(node in line for node in nodes), line
    for folder in sorted(out.glob("assembly_*")):
        labels, meta = read_assembly(folder)
        assert verify_labels(labels).valid
        method = json.loads((folder / "assembly.json").read_text())["method"]
        assert method["workers"] == 2 and method["ray"] is True
        assert meta["seed"] in {worker_seed(0, 0), worker_seed(0, 1)}
    assert not actor_nodes(api, "_RayWorker")


def test_solve_on_an_address_nothing_answers_is_one_line_at_once(tmp_path):
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # free once closed: nothing listens there
    started = time.monotonic()
    code, _, err = run_cli(
        "solve", "--shape", "cube4", "--pieces", "7", "--workers", "2", "--address", f"127.0.0.1:{port}",
        "--out", str(tmp_path / "o"),
    )  # fmt: skip
    assert code == 2 and time.monotonic() - started < 30
    assert err.strip().startswith(f"rllock: error: cannot reach the Ray cluster at 127.0.0.1:{port}: ")
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "o").exists()
