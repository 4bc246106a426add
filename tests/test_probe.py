"""The bounded probe a failed `solve` runs (`rllock.search.probe`): the tasks near a failed one, nearest
first, and the nearest that works, without waiting for the others."""

from __future__ import annotations

import time

from helpers import run_cli

from rllock.core.shapes import load_shape
from rllock.core.verifier import verify_labels
from rllock.files.assembly import read_assembly
from rllock.search.probe import Candidate, nearby, probe, suggestions


def test_nearby_tasks_come_nearest_first_within_the_shape():
    assert [c.pieces for c in nearby(40, 485)] == [41, 39, 42, 38, 36, 32, 27, 20]
    with_thicker = nearby(40, 485, thicken=3)
    assert with_thicker[:3] == [Candidate(41), Candidate(39), Candidate(40, 3)]
    # K stays between 2 and N, and the failed K itself is not offered again.
    assert [c.pieces for c in nearby(3, 4)] == [4, 2]


def test_suggestions_go_from_pieces_of_20_voxels_to_larger_ones():
    assert [c.pieces for c in suggestions(548)] == [27, 22, 18, 14, 9, 7, 5]
    assert [c.pieces for c in suggestions(64)] == [3, 2]  # K from 2 up, each once
    assert [c.pieces for c in suggestions(18_198)] == [200, 152]  # at most 200 pieces


def test_solve_without_pieces_takes_a_k_the_probe_found_and_says_so(tmp_path):
    out = tmp_path / "o"
    code, stdout, stderr = run_cli("solve", "--shape", "cube5", "--out", str(out))
    # N = 125: pieces of about 20 voxels are K = 6, found at once.
    assert code == 0 and "solve: 1 valid assembly of cube5 K=6 in" in stdout, stderr
    assert "no --pieces: trying pieces of 20, 25, 30, 40, 60, 80, 120 voxels" in stderr
    assert "K=6: pieces of 20, the last 25; this search found one in" in stderr
    assert verify_labels(read_assembly(out / "assembly_001")[0]).valid
    code, _, stderr = run_cli("solve", "--shape", "cube5", "--probe", "0", "--out", str(tmp_path / "p"))
    assert code == 2 and stderr.strip().endswith(
        "give --pieces: without it solve tries piece counts, which --probe 0 turns off"
    ), stderr


def test_the_probe_offers_the_nearest_that_works_and_stops_the_others():
    """desia-bunny K=81 (a last piece of 86) is found in a second or two; K=80 is not within a minute
    (tests/test_first_contact.py). Listed first, K=81 is offered without waiting for K=80's search."""
    grid = load_shape("desia-bunny")
    started = time.monotonic()
    found = probe(grid, "straight", [Candidate(81), Candidate(80)], seed=0, seconds=60, budget=60, workers=2)
    assert found is not None and found.candidate == Candidate(81)
    assert (found.piece_size, found.last_size) == (11, 86) and found.seconds < 30
    assert time.monotonic() - started < 45  # K=80's search was stopped, not waited for
    # Nothing near enough works within the time given: no offer.
    assert probe(grid, "straight", [Candidate(80)], seed=0, seconds=1, budget=1, workers=1) is None
