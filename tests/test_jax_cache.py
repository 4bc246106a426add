"""JAX's persistent compilation cache (`rllock.process.setup_jax_cache`): a second process finds what a
first one compiled, the off switch keeps the folder empty, and `rllock bench paper` says how its arms
started."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
from pathlib import Path

from rllock.orchestration.bench.arms import Arm, cache_start
from rllock.orchestration.bench.paper import PAPER_TASKS, PaperRow, format_paper_table, row_json

# Compiles the network's forward pass (a program without host callbacks, so JAX may cache it) in a
# fresh process set up as the CLI does, and reports what it found in the cache.
PROGRAM = """
import json
from rllock.process import jax_cache_entries, setup_jax_cache

folder = setup_jax_cache()
import jax

hits = []
jax.monitoring.register_event_listener(
    lambda event, **_: hits.append(event) if event == "/jax/compilation_cache/cache_hits" else None
)
from rllock.search.network import NetConfig, PolicyValueNet, init_params, planes_of

net = NetConfig(canvas=4, features=(4, 8))
params = init_params(net, jax.random.PRNGKey(0))
planes = jax.numpy.ones((2, 4, 4, 4, planes_of(net)))
jax.block_until_ready(jax.jit(lambda p, x: PolicyValueNet(net).apply({"params": p}, x))(params, planes))
print(json.dumps({"folder": None if folder is None else str(folder), "hits": len(hits),
                  "entries": jax_cache_entries()}))
"""


def _compile_in_a_new_process(tmp_path: Path, **env: str) -> dict:
    clean = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_", "RLLOCK_JAX"))}
    proc = subprocess.run(
        [sys.executable, "-c", PROGRAM],
        env={**clean, "XDG_CACHE_HOME": str(tmp_path / "xdg"), **env},
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_a_second_process_finds_the_first_ones_compiled_programs_in_the_users_folder(tmp_path):
    folder = tmp_path / "xdg" / "rllock" / "jax"  # $XDG_CACHE_HOME/rllock/jax: RLLOCK_JAX_CACHE is unset
    first = _compile_in_a_new_process(tmp_path)
    assert first["folder"] == str(folder) and first["hits"] == 0 and first["entries"] > 0
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700  # JAX runs what it reads there: owner only
    second = _compile_in_a_new_process(tmp_path)
    assert second["hits"] >= first["entries"]  # every program the first compiled, read back
    assert second["entries"] == first["entries"]  # and none compiled again


def test_the_off_switch_leaves_the_cache_folder_empty(tmp_path):
    off = _compile_in_a_new_process(tmp_path, RLLOCK_JAX_CACHE="off")
    assert off == {"folder": None, "hits": 0, "entries": None}
    folder = tmp_path / "xdg" / "rllock" / "jax"
    assert not folder.exists() or not any(folder.iterdir())


def test_the_cli_sets_the_cache_up_where_the_variable_moves_it(tmp_path):
    folder = tmp_path / "moved"
    env = {**os.environ, "RLLOCK_JAX_CACHE": str(folder)}
    proc = subprocess.run(
        [sys.executable, "-m", "rllock.orchestration.cli", "verify", str(tmp_path / "missing.json")],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2 and folder.is_dir()


def test_bench_paper_says_how_each_network_arm_started():
    assert cache_start(None, None) == "off"
    assert cache_start(3, 9) == "cold"  # it compiled six programs the cache lacked
    assert cache_start(9, 9) == "warm"
    row = PaperRow(
        PAPER_TASKS["cube4-k7"],
        "cube4-k7",
        11,
        Arm(5, 64, 14.0, "cold"),
        Arm(1, 64, 30.0, "warm"),
        Arm(5, None, 0.5),
    )
    table = format_paper_table([row], dict(count=5, batch=64, time_limit=300), "rllock bench paper")
    assert "| cube4-k7 | 2.8 (5) | 30.0 (1) | 0.1 (5) | cold / warm | 3.0 | 0.6 |" in table
    doc = row_json(row)
    assert doc["trained"]["cache"] == "cold" and doc["untrained"]["cache"] == "warm"
    assert doc["solver"]["cache"] is None
