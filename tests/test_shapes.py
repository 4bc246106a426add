from __future__ import annotations

import numpy as np
import pytest

from rllock.core.shapes import VENDORED_SHAPES, data_path, load_shape, piece_size, read_puz_labels, write_puz
from rllock.errors import RLLockError


def test_builtins_have_the_documented_sizes():
    assert load_shape("cube4").sum() == 64
    assert load_shape("cube6").shape == (6, 6, 6)
    assert load_shape("box:4x3x2").shape == (4, 3, 2)
    ring = load_shape("ring")
    assert ring.shape == (8, 8, 3) and ring.sum() == 144
    assert not ring[2:6, 2:6, :].any() and ring[0:2].all()


@pytest.mark.parametrize(
    "name,count",
    [
        ("desia_Cube_4x4x4_origin.puz", 64),
        ("desia_Cube_5x5x5_origin.puz", 125),
        ("desia_Cube_hollow_4x4x4_origin.puz", 56),
        ("desia_bunny_origin.puz", 966),
        ("desia_dog_origin.puz", 581),
        ("highlevel_Sofa_7x8x6.vol", 168),
    ],
)
def test_published_shapes_load_with_their_voxel_counts(data, name, count):
    assert load_shape(str(data / "shapes" / name)).sum() == count


@pytest.mark.parametrize(
    "name,file",
    [
        ("bunny", "highlevel_Bunny_11x10x8.vol"),
        ("cubeweird", "highlevel_CubeWeird_6x6x6.vol"),
        ("mario", "highlevel_Mario_12x16x4.vol"),
        ("shelf", "highlevel_Shelf_9x9x4.vol"),
        ("sofa", "highlevel_Sofa_7x8x6.vol"),
        ("spider", "highlevel_Spider_12x13x6.vol"),
        ("desia-cube4", "desia_Cube_4x4x4_origin.puz"),
        ("desia-cube5", "desia_Cube_5x5x5_origin.puz"),
        ("desia-hollow-cube4", "desia_Cube_hollow_4x4x4_origin.puz"),
        ("desia-bunny", "desia_bunny_origin.puz"),
        ("desia-dog", "desia_dog_origin.puz"),
    ],
)
def test_vendored_shapes_load_by_name_from_any_directory(data, name, file, tmp_path, monkeypatch):
    from_file = load_shape(str(data / "shapes" / file))
    # A user's working directory holds no data: the name must resolve inside the installed package.
    monkeypatch.chdir(tmp_path)
    by_name = load_shape(name)
    assert by_name.sum() == from_file.sum() and np.array_equal(by_name, from_file)


def test_every_vendored_shape_has_a_name_and_a_file(data):
    files = {p.name for p in (data / "shapes").iterdir() if p.suffix in (".puz", ".vol")}
    assert set(VENDORED_SHAPES.values()) == files
    assert data == data_path("") and (data / "published" / "Cube_4x4x4_K9.puz").is_file()


def test_vol_orientation_is_x_fastest(data):
    # The sofa file's first z-slice, first y-row is "1 1 0 0 0 1 1": x varies along the line.
    grid = load_shape(str(data / "shapes" / "highlevel_Sofa_7x8x6.vol"))
    assert grid.shape == (7, 8, 6)
    assert list(grid[:, 0, 0].astype(int)) == [1, 1, 0, 0, 0, 1, 1]


def test_puz_round_trip_keeps_labels_and_axes(tmp_path):
    rng = np.random.default_rng(0)
    labels = rng.integers(0, 5, size=(3, 4, 5))
    write_puz(tmp_path / "a.puz", labels)
    assert np.array_equal(read_puz_labels(tmp_path / "a.puz"), labels)


def test_npy_shapes_and_nonzero_puz_values(tmp_path):
    grid = np.zeros((3, 3, 3), dtype=bool)
    grid[0, :, 0] = True
    np.save(tmp_path / "line.npy", grid)
    assert load_shape(str(tmp_path / "line.npy")).shape == (1, 3, 1)
    write_puz(tmp_path / "labels.puz", np.array([[[3, 7]]]))
    assert load_shape(str(tmp_path / "labels.puz")).sum() == 2


@pytest.mark.parametrize(
    "content,message",
    [
        ("4 4", "header"),
        ("2 1 1\n1 x", "integers"),
        ("2 1 1\n1 1 1", "found 3 values"),
        ("2 1 1\n0 0", "empty"),
        ("3 1 1\n1 0 1", "not 6-connected"),
    ],
)
def test_bad_shape_files_are_clear_errors(tmp_path, content, message):
    path = tmp_path / "bad.puz"
    path.write_text(content)
    with pytest.raises(RLLockError, match=message):
        load_shape(str(path))


def test_unknown_names_and_missing_files():
    with pytest.raises(RLLockError, match="unknown shape") as err:
        load_shape("dodecahedron")
    # One line that lists the names a user could have meant, the vendored ones included.
    assert "\n" not in str(err.value) and "sofa" in str(err.value) and "desia-dog" in str(err.value)
    with pytest.raises(RLLockError, match="no such file"):
        load_shape("/nonexistent/shape.vol")


def test_piece_count_bounds():
    assert piece_size(64, 7) == 9
    with pytest.raises(RLLockError, match="at least 2"):
        piece_size(64, 1)
    with pytest.raises(RLLockError, match="larger than"):
        piece_size(8, 9)
