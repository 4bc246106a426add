from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import run_cli

from rllock.core.env import make_task
from rllock.core.shapes import read_puz_labels
from rllock.core.verifier import verify_labels
from rllock.files.assembly import read_assembly, write_assembly
from rllock.search.restarts import luby
from rllock.search.solver import search


def test_luby_sequence():
    assert [luby(i) for i in range(1, 16)] == [1, 1, 2, 1, 1, 2, 4, 1, 1, 2, 1, 1, 2, 4, 8]


def _first(task, seed, count=2):
    return [f.labels for f, _ in zip(search(task, seed=seed, time_limit=60), range(count))]


def test_same_seed_same_assemblies():
    task = make_task("cube4", 7)
    a, b, c = _first(task, 3), _first(task, 3), _first(task, 4)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not np.array_equal(a[0], c[0])


@pytest.mark.parametrize(
    "shape,k,removal",
    [("cube4", 7, "straight"), ("cube5", 13, "straight"), ("ring", 15, "straight"), ("cube4", 8, "path")],
)
def test_found_assemblies_have_equal_pieces_and_pass_the_verifier(shape, k, removal):
    task = make_task(shape, k, removal)
    labels = _first(task, 0, 1)[0]
    n = task.size // k
    sizes = np.bincount(labels.ravel())[1:]
    assert len(sizes) == k and (sizes[:-1] == n).all() and sizes[-1] == task.size - (k - 1) * n
    assert verify_labels(labels, removal).valid


def test_solve_command_writes_verified_files(tmp_path):
    code, out, err = run_cli(
        "solve", "--shape", "cube4", "--pieces", "7", "--count", "2", "--seed", "5", "--out", str(tmp_path)
    )
    assert code == 0 and "per valid assembly" in out
    assert "smallest last piece" not in err  # K = 7 on 64 voxels: pieces of 9, the last of 10
    folders = sorted(tmp_path.glob("assembly_*"))
    assert len(folders) == 2
    for folder in folders:
        doc = json.loads((folder / "assembly.json").read_text())
        assert doc["verification"]["valid"] and doc["K"] == 7 and doc["n"] == 9 and doc["seed"] == 5
        assert doc["method"]["name"] == "search" and doc["removal"] == "straight"
        labels, _ = read_assembly(folder / "assembly.json")
        assert np.array_equal(labels, read_puz_labels(folder / "assembly.puz"))
        assert "verified valid" in (folder / "assembly.puz").read_text()
        assert run_cli("verify", str(folder / "assembly.puz"))[0] == 0


def test_solve_says_when_the_last_piece_takes_many_spare_voxels_and_which_k_does_not(tmp_path):
    code, _, err = run_cli("solve", "--shape", "cube6", "--pieces", "20", "--out", str(tmp_path / "o"))
    assert code == 0
    assert "K=20 on 216 voxels: pieces of 10 and a last piece of 26" in err, err
    assert "K=21 gives pieces of 10 and the smallest last piece (16)" in err, err


def test_invalid_assemblies_are_never_written(tmp_path):
    with pytest.raises(AssertionError, match="refusing"):
        write_assembly(
            tmp_path / "bad",
            np.array([1, 2, 3]).reshape(3, 1, 1),
            removal="straight",
            shape="box:3x1x1",
            method={"name": "test"},
            seed=0,
            timings={},
        )
    assert not (tmp_path / "bad").exists()
