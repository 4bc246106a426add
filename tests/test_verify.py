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

    # Valid only under path, and its pieces have n = floor(N/K) voxels each, as assembly.json requires.
    labels = read_puz_labels(data / "published" / "Cube_Hollow_4x4x4_K7.puz")
    write_assembly(
        tmp_path, labels, removal="path", shape="hollow", method={"name": "published"}, seed=0, timings={}
    )
    assert run_cli("verify", str(tmp_path / "assembly.json"))[0] == 0
    assert run_cli("verify", str(tmp_path / "assembly.json"), "--removal", "straight")[0] == 1


@pytest.fixture(scope="module")
def cube4_k7() -> np.ndarray:
    return next(search(make_task("cube4", 7), seed=0, time_limit=60)).labels


def _edited(tmp_path, labels: np.ndarray, edit) -> str:
    """An assembly.json of `labels` (verified when written) after `edit(doc, grid)` changed it by hand;
    `grid` is the label grid [x, y, z], written back x fastest."""
    from rllock.core.shapes import to_xfastest
    from rllock.files.assembly import write_assembly

    write_assembly(tmp_path / "a", labels, removal="straight", shape="cube4", method={}, seed=0, timings={})
    path = tmp_path / "a" / "assembly.json"
    doc = json.loads(path.read_text())
    grid = labels.copy()
    edit(doc, grid)
    doc["labels"] = [int(v) for v in to_xfastest(grid)]
    path.write_text(json.dumps(doc))
    return str(path)


def _first_voxel(grid: np.ndarray, piece: int) -> tuple[int, ...]:
    return tuple(int(c) for c in np.argwhere(grid == piece)[0])


def test_an_assembly_json_that_no_longer_matches_its_counts_is_refused(tmp_path, cube4_k7):
    assert run_cli("verify", _edited(tmp_path / "same", cube4_k7, lambda doc, grid: None))[0] == 0

    def zero_one(doc, grid):
        grid[_first_voxel(grid, 2)] = 0

    code, out, err = run_cli("verify", _edited(tmp_path / "zeroed", cube4_k7, zero_one))
    assert code == 2 and out == "" and err.count("\n") == 1, err
    assert "says N = 64, but its labels fill 63 voxels" in err

    def zero_one_and_fix_n(doc, grid):
        zero_one(doc, grid)
        doc["N"] = 63  # n stays floor(63/7) = 9, but piece 2 now has 8

    code, _, err = run_cli("verify", _edited(tmp_path / "counted", cube4_k7, zero_one_and_fix_n))
    assert code == 2 and "piece 2 has 8 voxels, not n = 9" in err, err

    def wrong_n(doc, grid):
        doc["n"] = 8

    code, _, err = run_cli("verify", _edited(tmp_path / "n", cube4_k7, wrong_n))
    assert code == 2 and "says n = 8, but floor(N/K) = floor(64/7) = 9" in err, err


@pytest.mark.parametrize("value", [99, -1, 8])
def test_a_label_out_of_range_is_named_with_its_voxel(tmp_path, cube4_k7, value):
    where = _first_voxel(cube4_k7, 7)

    def relabel(doc, grid):
        grid[where] = value

    code, _, err = run_cli("verify", _edited(tmp_path, cube4_k7, relabel))
    assert code == 2 and err.count("\n") == 1, err
    assert f"label {value} at voxel {where} is not a piece number 1..7" in err, err


def test_a_stray_label_in_a_puz_is_named_not_counted_as_missing_pieces(tmp_path, cube4_k7):
    grid = cube4_k7.copy()
    where = _first_voxel(grid, 7)
    grid[where] = 99
    write_puz(tmp_path / "stray.puz", grid)
    code, _, err = run_cli("verify", str(tmp_path / "stray.puz"))
    assert code == 2 and err.strip() == f"rllock: error: label 99 at voxel {where} is not a piece number 1..7"


def test_verify_json_answers_bad_input_with_one_json_object(tmp_path):
    (tmp_path / "bad.json").write_text("{not json")
    for name, needle in (("bad.json", "malformed assembly file"), ("missing.puz", "no such file")):
        path = tmp_path / name
        code, out, err = run_cli("verify", str(path), "--json")
        assert code == 2 and out.count("\n") == 1, out
        assert json.loads(out) == {
            "file": str(path),
            "valid": None,
            "error": err.strip().removeprefix("rllock: error: "),
        }
        assert needle in json.loads(out)["error"]


def _variants(labels: np.ndarray, rng: np.random.Generator, count: int):
    """`labels` and `count` corruptions of it: two pieces' ids swapped (the order changes, so stages fail
    every way), or a voxel given to a neighbouring piece (pieces and rests may fall apart)."""
    yield labels
    k = int(labels.max())
    for t in range(count):
        out = labels.copy()
        if t % 2 == 0:
            a, b = rng.choice(np.arange(1, k + 1), 2, replace=False)
            out[labels == a], out[labels == b] = b, a
        else:
            filled = np.argwhere(labels > 0)
            v = filled[rng.integers(len(filled))]
            for d in rng.permutation(len(ref.DIRECTIONS)):
                u = v + ref.DIRECTIONS[d]
                if (
                    np.all(u >= 0)
                    and np.all(u < labels.shape)
                    and labels[tuple(u)] not in (0, labels[tuple(v)])
                ):
                    out[tuple(v)] = labels[tuple(u)]
                    break
        if len(np.unique(out[out > 0])) == k:  # ids still 1..K: a verdict, not a bad-input error
            yield out


EVERY_CHECK = {None, "connected", "removable", "interlocking"}


@pytest.mark.parametrize(
    "shape,k,removal", [("cube4", 7, "straight"), ("cube5", 13, "path"), ("desia-bunny", 40, "straight")]
)
def test_verdicts_equal_the_reference_checkers_stage_by_stage(shape, k, removal, data):
    """The verifier's verdicts, disassembly moves included, are those of the reference checkers applied to
    every stage plainly, on solver assemblies, published ones and corruptions of both that fail at every
    kind of stage and check."""
    from helpers import reference_verdict

    task = make_task(shape, k, removal)
    rng = np.random.default_rng(k)
    assemblies = [f.labels for f, _ in zip(search(task, seed=2, time_limit=60), range(2))]
    assemblies.append(read_puz_labels(data / "published" / "Cube_4x4x4_K9.puz"))
    checks = set()
    for base in assemblies:
        for labels in _variants(base, rng, 12):
            verdict = verify_labels(labels, removal)
            got = (verdict.valid, verdict.failed_stage, verdict.failed_check, verdict.disassembly)
            assert got == reference_verdict(labels, removal)
            checks.add(verdict.failed_check)
    assert checks == EVERY_CHECK
