from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import run_cli

from rllock.core import reference_checkers as ref
from rllock.core.env import make_task
from rllock.core.shapes import read_puz_labels, write_puz
from rllock.core.verifier import verify_labels
from rllock.search.solver import search

PUBLISHED = [
    "Cube_4x4x4_K9.puz",
    "Cube_4x4x4_K9_01.puz",
    "Cube_Hollow_4x4x4_K7.puz",
    "cube_5x5x5_K16.puz",
    "cartoon_dog.puz",
]


def replay_disassembly(labels: np.ndarray, verdict) -> None:
    """Move each piece along its reported moves, one unit step at a time, and check that it never
    overlaps a piece still in place and ends outside their bounding box."""
    k = verdict.pieces
    for entry in verdict.disassembly:
        i = entry["piece"]
        piece = np.argwhere(labels == i)
        rest_cells = np.argwhere(labels > i)
        rest = {tuple(v) for v in rest_cells.tolist()}
        offset = np.zeros(3, dtype=int)
        for move in entry["moves"]:
            step = np.array(ref.DIRECTIONS[ref.DIRECTION_NAMES.index(move["direction"])])
            for _ in range(move["steps"]):
                offset += step
                assert not any(tuple(v) in rest for v in (piece + offset).tolist()), f"piece {i} collides"
        moved = piece + offset
        lo, hi = rest_cells.min(axis=0), rest_cells.max(axis=0)
        assert any((moved[:, a].max() < lo[a]) or (moved[:, a].min() > hi[a]) for a in range(3)), (
            f"piece {i} stuck"
        )
    assert [e["piece"] for e in verdict.disassembly] == list(range(1, k))


@pytest.mark.parametrize("name", PUBLISHED)
def test_published_assemblies_are_valid_under_path_removal(data, name):
    labels = read_puz_labels(data / "published" / name)
    verdict = verify_labels(labels, "path")
    assert verdict.valid and verdict.failed_stage is None
    replay_disassembly(labels, verdict)


def test_published_cube_fails_straight_removal_at_stage_3(data):
    verdict = verify_labels(read_puz_labels(data / "published" / "Cube_4x4x4_K9.puz"), "straight")
    assert (verdict.valid, verdict.failed_stage, verdict.failed_check) == (False, 3, "removable")


@pytest.mark.parametrize(
    "row,stage,check",
    [
        ([1, 2, 1], 1, "connected"),  # piece 1 in two parts
        ([2, 1, 2], 1, "connected"),  # the rest R_1 in two parts
        ([1, 2, 3], 2, "interlocking"),
    ],  # a bar of three: everything slides along y
)
def test_first_failure_is_reported_with_its_stage(row, stage, check):
    labels = np.array(row).reshape(3, 1, 1)
    verdict = verify_labels(labels)
    assert (verdict.valid, verdict.failed_stage, verdict.failed_check) == (False, stage, check)


@pytest.mark.parametrize("removal", ["straight", "path"])
def test_solver_assemblies_replay_their_disassembly(removal):
    task = make_task("cube4", 7, removal)
    for found, _ in zip(search(task, seed=1, time_limit=60), range(2)):
        verdict = verify_labels(found.labels, removal)
        assert verdict.valid
        replay_disassembly(found.labels, verdict)
        if removal == "straight":
            assert all(len(e["moves"]) == 1 for e in verdict.disassembly)


def test_verify_command_exit_codes_and_json(data, tmp_path):
    cube = str(data / "published" / "Cube_4x4x4_K9.puz")
    code, out, _ = run_cli("verify", cube, "--removal", "path", "--json")
    doc = json.loads(out)
    assert code == 0 and doc["valid"] and doc["removal"] == "path" and doc["failed_stage"] is None
    assert len(doc["disassembly"]) == doc["pieces"] - 1 == 8
    code, out, _ = run_cli("verify", cube, "--json")
    doc = json.loads(out)
    assert code == 1 and (doc["failed_stage"], doc["failed_check"]) == (3, "removable")
    write_puz(tmp_path / "gap.puz", np.array([1, 3, 3]).reshape(3, 1, 1))
    code, out, err = run_cli("verify", str(tmp_path / "gap.puz"))
    assert code == 2 and "1..K" in err and "Traceback" not in err


def test_verify_uses_the_removal_mode_an_assembly_json_names(data, tmp_path):
    from rllock.files.assembly import write_assembly

    labels = read_puz_labels(data / "published" / "Cube_4x4x4_K9.puz")  # valid only under path
    write_assembly(
        tmp_path, labels, removal="path", shape="cube4", method={"name": "published"}, seed=0, timings={}
    )
    assert run_cli("verify", str(tmp_path / "assembly.json"))[0] == 0
    assert run_cli("verify", str(tmp_path / "assembly.json"), "--removal", "straight")[0] == 1
