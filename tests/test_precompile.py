"""The install-time compile (`rllock.core.precompile`) covers what the commands then run: after it, the
search (plain, deep, closed proposal, both removal modes, on threads), MCTS's candidates and tables that
came through Ray (read-only) compile no new numba signature, so none of them compiles inside a time
limit."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
from numba.core.registry import CPUDispatcher

from rllock.core import (
    compiled_checkers,
    compiled_interlocking,
    compiled_proposals,
    compiled_sampler,
    winding,
)
from rllock.core.env import candidates_many, initial_state, make_task, sample_accepted
from rllock.core.numba_cache import (
    CORE,
    DAY,
    USED,
    CoreSourcesLocator,
    numba_cache_root,
    prune,
    sources_digest,
)
from rllock.core.precompile import _layouts, compile_all
from rllock.search.solver import solve


def _signatures() -> set[tuple[str, str]]:
    found = set()
    for module in (compiled_checkers, compiled_interlocking, compiled_proposals, compiled_sampler, winding):
        for name, value in vars(module).items():
            if isinstance(value, CPUDispatcher):
                found |= {(f"{module.__name__}.{name}", str(sig)) for sig in value.signatures}
    return found


def test_the_layouts_are_the_tables_as_built_and_read_only_with_the_same_values():
    task = make_task("cube4", 6)
    built, read_only = _layouts(task)
    assert built is task
    tables = [a for a in task.topology.arrays if isinstance(a, np.ndarray)]
    assert all(a.flags.c_contiguous and a.flags.writeable for a in tables)
    frozen = [a for a in read_only.topology.arrays if isinstance(a, np.ndarray)]
    assert not any(a.flags.writeable for a in frozen)
    assert all(np.array_equal(a, b) for a, b in zip(tables, frozen))


def test_after_the_precompile_the_search_mcts_and_ray_tables_compile_nothing_new():
    compile_all()
    before = _signatures()
    # The entry points (their callees are compiled into them, and a cached entry loads without them).
    entries = {
        "rllock.core.compiled_sampler." + f
        for f in (
            "sample_and_check_mixed",
            "candidates_many",
            "candidates_serial",
            "remainder_growth",
            "distinct_rows",
        )
    } | {"rllock.core.compiled_checkers.check_chunks", "rllock.core.winding._winding_many"}
    assert entries <= {name for name, _ in before}
    for removal in ("straight", "path"):
        assert solve(make_task("cube4", 6, removal=removal), time_limit=30, seed=0)
        # Deep mode (the default: wide seeds, thin growth, the remainder's surface), the closed proposal.
        solve(make_task("box:4x4x8", 30, removal=removal), time_limit=0.5, seed=0)
        solve(make_task("box:8x8x8", 8, removal=removal), time_limit=0.5, seed=0, threads=2)
    task = make_task("ring", 15)
    states = [initial_state(task)] * 2
    candidates_many(task, states, np.arange(2), num_samples=16, max_candidates=4)
    frozen = _layouts(task)[1]  # as a Ray actor receives it
    sample_accepted(frozen, initial_state(frozen), seed=1, num_samples=16, closed_share=0.5)
    solve(frozen, time_limit=0.5, seed=0)
    assert _signatures() - before == set()


def test_the_cache_is_per_user_and_per_version_of_the_core_sources(tmp_path):
    """A copy of the sources elsewhere (a Ray job's unpacked working folder) has the same folder and
    loads what was compiled; a change to any core file is a new folder."""
    folder = numba_cache_root() / sources_digest(CORE)
    assert compiled_sampler.sample_and_check_mixed.stats.cache_path == str(folder)
    assert (
        CoreSourcesLocator.from_function(
            test_the_cache_is_per_user_and_per_version_of_the_core_sources, __file__
        )
        is None
    )
    copy = tmp_path / "rllock"
    shutil.copytree(CORE.parent, copy, ignore=shutil.ignore_patterns("__pycache__", "data", "checkpoints"))
    assert sources_digest(copy / "core") == sources_digest(CORE)
    (copy / "core" / "shapes.py").write_text((CORE / "shapes.py").read_text() + "\n# changed\n")
    sources_digest.cache_clear()
    assert sources_digest(copy / "core") != sources_digest(CORE)
    (copy / "core" / "shapes.py").write_text((CORE / "shapes.py").read_text())
    sources_digest.cache_clear()
    compile_all()  # the cache holds every entry point (it compiles only where sources changed since)
    # The copy, imported in a new process instead of the installed package, compiles nothing.
    script = f"""
import sys
sys.meta_path[:] = [f for f in sys.meta_path if "editable" not in str(f).lower()]
sys.path.insert(0, {str(tmp_path)!r})
from rllock.core import compiled_sampler
from rllock.core.precompile import compile_all
assert compiled_sampler.__file__.startswith({str(tmp_path)!r}), compiled_sampler.__file__
compile_all()
stats = compiled_sampler.sample_and_check_mixed.stats
print(stats.cache_path, sum(stats.cache_hits.values()), sum(stats.cache_misses.values()))
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    path, hits, misses = done.stdout.split()
    assert Path(path) == folder and int(hits) > 0 and int(misses) == 0
    assert not list((copy / "core").glob("__pycache__/*.nb*"))


def test_the_folders_of_other_versions_unused_for_stale_days_are_removed(tmp_path):
    now, current = 1_000 * DAY, "0123456789abcdef"
    ages = {"aaaaaaaaaaaaaaaa": 40, "bbbbbbbbbbbbbbbb": 5, "cccccccccccccccc": 40, "notadigest": 40}
    for name, days in ages.items():
        (tmp_path / name).mkdir()
        stamp = now - days * DAY
        if name == "cccccccccccccccc":  # unmarked: its own modification time decides
            os.utime(tmp_path / name, (stamp, stamp))
        else:
            (tmp_path / name / USED).touch()
            os.utime(tmp_path / name / USED, (stamp, stamp))
    (tmp_path / "bbbbbbbbbbbbbbbb" / "index.nbi").write_bytes(b"x")
    assert sorted(p.name for p in prune(tmp_path, current, now)) == ["aaaaaaaaaaaaaaaa", "cccccccccccccccc"]
    assert sorted(p.name for p in tmp_path.iterdir()) == [current, "bbbbbbbbbbbbbbbb", "notadigest"]
    assert (tmp_path / current / USED).stat().st_mtime == now
    assert prune(tmp_path, current, now + 0.5 * DAY) == []  # marked at most once a day
    assert (tmp_path / current / USED).stat().st_mtime == now
    # The version in use is never removed, and a version used again within STALE_DAYS is kept.
    assert prune(tmp_path, "bbbbbbbbbbbbbbbb", now + 29 * DAY) == []
    assert [p.name for p in prune(tmp_path, "bbbbbbbbbbbbbbbb", now + 31 * DAY)] == [current]
    assert (numba_cache_root() / sources_digest(CORE) / USED).exists()  # this import marked its own
