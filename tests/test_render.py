"""`rllock show`: the PNG, the GIF that follows the verified moves, and the self-contained HTML viewer."""

from __future__ import annotations

import argparse
import subprocess
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from rllock.core.reference_checkers import DIRECTION_NAMES, DIRECTIONS
from rllock.core.shapes import read_puz_labels, write_puz
from rllock.core.verifier import verify_labels
from rllock.errors import RLLockError
from rllock.files import render
from rllock.files.assembly import write_assembly
from rllock.files.render import (
    disassembly_steps,
    draw_png,
    exploded_label_points,
    exploded_offsets,
    label_point,
    piece_colors,
    pieces_of,
    touching_pieces,
    view_direction,
    write_gif,
    write_html,
    write_picture,
)
from rllock.orchestration.cli.assemblies import add_commands

CHROMIUM = Path("/usr/bin/chromium")


@pytest.fixture(scope="module")
def labels() -> np.ndarray:
    from rllock.core.env import make_task
    from rllock.search.solver import search

    return next(search(make_task("cube4", 7), seed=0, time_limit=30)).labels


def _run(*argv: str) -> int:
    parser = argparse.ArgumentParser()
    add_commands(parser.add_subparsers(required=True))
    args = parser.parse_args(list(argv))
    return args.func(args)


def _colourful_pixels(image: Image.Image) -> int:
    """Pixels of a clearly saturated colour: the pieces, not white paper, grey axes or black text."""
    hsv = np.asarray(image.convert("RGB").convert("HSV")).reshape(-1, 3)
    return int(((hsv[:, 1] > 80) & (hsv[:, 2] > 60)).sum())


def test_piece_colours_are_distinct_and_touching_pieces_never_share_one():
    slabs = (np.arange(216) * 24 // 216 + 1).reshape(6, 6, 6)
    colors = piece_colors(slabs)
    assert len(colors) == 24
    assert np.linalg.norm(colors[:, None] - colors[None], axis=-1)[np.triu_indices(24, 1)].min() > 0.02
    assert np.linalg.norm(colors[1:8, None] - colors[None, 1:8], axis=-1)[np.triu_indices(7, 1)].min() > 0.2
    # 1,728 pieces of 2x2x2 on a 24^3 cube, numbered in a random order: each piece touches up to 6 others,
    # and none of them has its colour, which are 24 distinct ones used about evenly.
    blocks = np.arange(12**3).reshape(12, 12, 12)
    order = np.random.default_rng(0).permutation(12**3) + 1
    labels = order[blocks].repeat(2, 0).repeat(2, 1).repeat(2, 2)
    colors = piece_colors(labels)
    assert len(colors) == 12**3 and len(np.unique(colors, axis=0)) == 24
    for i, touching in enumerate(touching_pieces(labels)):
        assert 3 <= len(touching) <= 6
        assert all(np.linalg.norm(colors[i] - colors[j]) > 0.02 for j in touching)
    assert np.bincount(np.unique(colors, axis=0, return_inverse=True)[1].ravel()).min() > 12**3 / 24 / 2


def test_png_shows_every_piece(tmp_path):
    # Any labelling with ids 1..K can be drawn; 25 slabs of a 6x6x6 cube stand in for a K=25 assembly.
    grid = (np.arange(216) * 25 // 216 + 1).reshape(6, 6, 6)
    draw_png(grid, tmp_path / "cube6.png", "straight")
    image = Image.open(tmp_path / "cube6.png")
    assert image.size == (900, 450)
    assert _colourful_pixels(image) > 0.1 * 900 * 450


def _seen_in(point: np.ndarray, scene: list[tuple[np.ndarray, np.ndarray]], view: np.ndarray) -> bool:
    """Reference: the ray from `point` (20 voxels long, in steps of 0.005) meets no voxel of the grids
    drawn at their offsets."""
    samples = point + np.arange(0.005, 20, 0.005)[:, None] * view
    for grid, off in scene:
        cells = np.floor(samples - off).astype(int)
        inside = np.all((cells >= 0) & (cells < grid.shape), axis=1)
        if grid[tuple(cells[inside].T)].any():
            return False
    return True


@pytest.mark.parametrize("corner", [(3, 0, 0), (3, 3, 0), (0, 3, 3), (3, 3, 3), (1, 0, 3), (3, 1, 2)])
def test_a_label_sits_on_the_nearest_face_the_camera_sees(corner):
    # A 5^3 cube whose key is a 2^3 block: wherever the block is, its label must sit on a face of it that
    # the camera sees (the demo's key, at the back, was labelled at its centre, over another piece).
    view = view_direction(24, -58)
    labels = np.full((5, 5, 5), 2)
    x, y, z = corner
    labels[x : x + 2, y : y + 2, z : z + 2] = 1
    key, solid = labels == 1, labels > 0
    at = label_point(key, solid, view, [(solid, np.zeros(3))])
    # Brute force over every face of the key: those the camera sees, nearest first.
    faces = [
        voxel + 0.5 + 0.5 * np.asarray(d)
        for voxel in np.argwhere(key)
        for d in DIRECTIONS
        if np.asarray(d) @ view > 0
        and _seen_in(voxel + 0.5 + 0.5 * np.asarray(d), [(solid, np.zeros(3))], view)
    ]
    assert faces, "every corner chosen shows the key"
    nearest = max(faces, key=lambda f: f @ view)
    np.testing.assert_allclose(at, nearest)
    # The centre, where the label used to go, is hidden for a block at the back.
    if corner == (3, 3, 0):
        assert not _seen_in(np.argwhere(key).mean(axis=0) + 0.5, [(solid & ~key, np.zeros(3))], view)


def test_a_piece_the_camera_cannot_see_is_labelled_at_its_centre():
    view = view_direction(24, -58)
    labels = np.full((3, 3, 3), 2)
    labels[1, 1, 1] = 1
    solid = labels > 0
    np.testing.assert_allclose(label_point(labels == 1, solid, view, [(solid, np.zeros(3))]), [1.5, 1.5, 1.5])
    # Alone (as in the exploded view, without the pieces around it) it shows its nearest face.
    alone = labels == 1
    at = label_point(alone, alone, view, [(alone, np.zeros(3))])
    nearest = max((1.5 + 0.5 * np.asarray(d)) @ view for d in DIRECTIONS)
    assert _seen_in(at, [(alone, np.zeros(3))], view) and np.isclose(at @ view, nearest)


def test_the_ray_test_is_exact_against_a_fine_march():
    # Grids at offsets that are not whole voxels, and points all around them: the cut ray against a march
    # 50 times finer than the steps the test once took (which missed corners).
    rng = np.random.default_rng(0)
    view = view_direction(24, -58)
    for _ in range(20):
        scene = [(rng.random((3, 4, 2)) < 0.5, rng.uniform(-2, 2, 3)) for _ in range(3)]
        points = rng.uniform(-3, 5, (30, 3))
        fine = [_seen_in(p, scene, view) for p in points]
        np.testing.assert_array_equal(render._unhidden(points, view, scene), fine)


def test_exploded_labels_sit_on_their_own_piece_where_the_camera_sees_it():
    # The demo's cube4 K=6 assembly (z, y, x): rounded to whole voxels, the exploded view put label 6 on
    # a face that piece 5, drawn in front of it, hides; the label showed on piece 5.
    labels = np.array(
        [
            [[6, 6, 5, 5], [6, 2, 5, 5], [6, 5, 5, 6], [6, 6, 6, 6]],
            [[6, 1, 1, 1], [2, 2, 1, 6], [3, 3, 5, 6], [3, 6, 4, 6]],
            [[1, 1, 1, 1], [2, 1, 5, 4], [2, 3, 5, 4], [3, 3, 4, 4]],
            [[2, 2, 1, 4], [2, 2, 4, 4], [2, 3, 5, 4], [3, 3, 3, 4]],
        ]
    ).transpose(2, 1, 0)
    view = view_direction(24, -58)
    offsets = exploded_offsets(pieces_of(labels), labels.shape)
    points = exploded_label_points(labels, offsets, view, 6)
    for i, (at, off) in enumerate(zip(points, offsets)):
        local = at - off
        # On a face of the piece: a whole coordinate on one axis with the piece on one side only.
        axis = int(np.argmin(np.abs(local - np.round(local))))
        inner, outer = np.floor(local).astype(int), np.floor(local).astype(int)
        inner[axis], outer[axis] = round(local[axis]) - 1, round(local[axis])
        sides = [labels[tuple(c)] if np.all(c >= 0) and np.all(c < 4) else 0 for c in (inner, outer)]
        assert (i + 1 in sides) and sides[0] != sides[1], (i + 1, local)
        assert _seen_in(at, [(labels == j + 1, o) for j, o in enumerate(offsets)], view), i + 1


def test_a_picture_writer_puts_a_picture_next_to_the_assembly(tmp_path, labels):
    write_assembly(
        tmp_path / "with",
        labels,
        removal="straight",
        shape="cube4",
        method={"name": "test"},
        seed=0,
        timings={},
        picture=write_picture,
    )
    assert Image.open(tmp_path / "with" / "assembly.png").format == "PNG"
    write_assembly(
        tmp_path / "without",
        labels,
        removal="straight",
        shape="cube4",
        method={"name": "test"},
        seed=0,
        timings={},
    )
    assert not (tmp_path / "without" / "assembly.png").exists()


def test_steps_follow_the_verified_moves(data):
    labels = read_puz_labels(data / "published" / "Cube_4x4x4_K9.puz")
    verdict = verify_labels(labels, "path")
    steps = disassembly_steps(verdict)
    assert len(steps) == 2 + sum(len(e["moves"]) for e in verdict.disassembly)
    assert steps[0].present.all() and not steps[0].offsets.any()
    assert steps[-1].present.tolist() == [False] * 8 + [True]
    for entry in verdict.disassembly:
        total = sum(
            np.asarray(DIRECTIONS[DIRECTION_NAMES.index(m["direction"])]) * m["steps"] for m in entry["moves"]
        )
        np.testing.assert_array_equal(steps[-1].offsets[entry["piece"] - 1], total)
    # Finer GIF frames pass through the same positions.
    fine = disassembly_steps(verdict, frames_per_move=3)
    assert len(fine) > len(steps)
    np.testing.assert_array_equal(fine[-1].offsets, steps[-1].offsets)


def test_gif_animates_the_disassembly(tmp_path, labels):
    verdict = verify_labels(labels, "straight")
    write_gif(labels, verdict, tmp_path / "a.gif")
    gif = Image.open(tmp_path / "a.gif")
    assert gif.n_frames == len(disassembly_steps(verdict, frames_per_move=3))
    first = np.asarray(gif.convert("RGB"))
    gif.seek(gif.n_frames - 1)
    last = np.asarray(gif.convert("RGB"))
    # The last frame holds only piece K: far fewer coloured pixels than the assembled first frame.
    assert _colourful_pixels(Image.fromarray(last)) < 0.7 * _colourful_pixels(Image.fromarray(first))


def test_html_is_self_contained(tmp_path, labels):
    write_html(labels, verify_labels(labels, "straight"), tmp_path / "a.html")
    text = (tmp_path / "a.html").read_text()
    assert "<script src=" not in text  # plotly.js is inlined, so no network is needed
    assert "Plotly.newPlot(" in text and "Plotly.addFrames(" in text
    assert "piece 1 (key)" in text


@pytest.mark.skipif(not CHROMIUM.exists(), reason="needs /usr/bin/chromium")
def test_html_renders_in_headless_chromium(tmp_path, labels):
    page, shot = tmp_path / "a.html", tmp_path / "shot.png"
    write_html(labels, verify_labels(labels, "straight"), page)
    subprocess.run(
        # --enable-unsafe-swiftshader keeps software WebGL on where Chromium no longer falls back to it
        # by itself.
        [
            str(CHROMIUM),
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--enable-unsafe-swiftshader",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            f"--user-data-dir={tmp_path / 'profile'}",
            f"--screenshot={shot}",
            "--window-size=800,600",
            "--virtual-time-budget=5000",
            page.as_uri(),
        ],
        capture_output=True,
        timeout=120,
        check=False,
    )
    image = Image.open(shot)
    # The pieces cover a good part of the 3D view; a page without WebGL output would be white and grey.
    assert _colourful_pixels(image) > 5000
    assert len(np.unique(np.asarray(image.convert("RGB")).reshape(-1, 3), axis=0)) > 50


def test_show_command_writes_all_three(tmp_path, data):
    source = data / "published" / "cartoon_dog.puz"
    out = {kind: tmp_path / f"dog.{kind}" for kind in ("png", "gif", "html")}
    assert _run("show", str(source), *[f"--{kind}={path}" for kind, path in out.items()]) == 0
    assert all(path.stat().st_size > 0 for path in out.values())


def test_show_uses_the_removal_mode_that_makes_a_puz_valid(tmp_path, data):
    # Valid only under path removal: the GIF follows the multi-move disassembly.
    source = data / "published" / "Cube_4x4x4_K9.puz"
    assert _run("show", str(source), "--gif", str(tmp_path / "a.gif")) == 0
    verdict = verify_labels(read_puz_labels(source), "path")
    assert Image.open(tmp_path / "a.gif").n_frames == len(disassembly_steps(verdict, frames_per_move=3))


def test_show_errors(tmp_path):
    (tmp_path / "bad.puz").write_text("3 1 1\n1 2 3\n")
    with pytest.raises(RLLockError, match="nothing to show"):
        _run("show", str(tmp_path / "bad.puz"))
    with pytest.raises(RLLockError, match="not a valid assembly"):
        _run("show", str(tmp_path / "bad.puz"), "--gif", str(tmp_path / "a.gif"))
    with pytest.raises(RLLockError, match="no such file"):
        _run("show", str(tmp_path / "missing.json"), "--png", str(tmp_path / "a.png"))
    # 201 pieces: animations that grow with K^2 are refused before any drawing; the PNG is drawn.
    write_puz(tmp_path / "big.puz", np.arange(1, 202).reshape(201, 1, 1))
    for kind in ("gif", "html"):
        with pytest.raises(
            RLLockError, match="animate at most 200 pieces and this assembly has 201: use --png"
        ):
            _run("show", str(tmp_path / "big.puz"), f"--{kind}", str(tmp_path / f"a.{kind}"))
        assert not (tmp_path / f"a.{kind}").exists()
    assert _run("show", str(tmp_path / "big.puz"), "--png", str(tmp_path / "big.png")) == 0
