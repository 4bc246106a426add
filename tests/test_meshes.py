"""Meshes both ways: closed .stl/.obj models to voxel shapes, and voxel pieces to watertight meshes."""

from __future__ import annotations

import itertools
import logging

import manifold3d as m3
import numpy as np
import pytest
import trimesh

from rllock.core.meshes import assembly_meshes, edge_only_contacts, piece_mesh, piece_volume
from rllock.core.shapes import load_shape
from rllock.errors import RLLockError


def _face_neighbours(labels: np.ndarray) -> set[tuple[int, int]]:
    pairs = set()
    for axis in range(3):
        a = np.moveaxis(labels, axis, 0)
        for p, q in zip(a[:-1].ravel(), a[1:].ravel()):
            if p and q and p != q:
                pairs.add((int(min(p, q)), int(max(p, q))))
    return pairs


def _manifold(mesh: trimesh.Trimesh) -> m3.Manifold:
    return m3.Manifold(
        m3.Mesh(
            vert_properties=np.asarray(mesh.vertices, dtype=np.float32),
            tri_verts=np.asarray(mesh.faces, dtype=np.uint32),
        )
    )


def test_box_mesh_voxelizes_to_a_full_box(tmp_path):
    trimesh.creation.box(extents=[4, 2, 1]).export(tmp_path / "box.stl")
    grid = load_shape(str(tmp_path / "box.stl"), resolution=4)
    assert grid.shape == (4, 2, 1) and grid.all()
    # Without a resolution the default (8 voxels along the longest side) applies.
    assert load_shape(str(tmp_path / "box.stl")).shape == (8, 4, 2)


def test_sphere_fills_its_inside(tmp_path):
    trimesh.creation.icosphere(subdivisions=3, radius=1.0).export(tmp_path / "ball.obj")
    grid = load_shape(str(tmp_path / "ball.obj"), resolution=10)
    assert grid.shape == (10, 10, 10)
    assert grid[5, 5, 5] and not grid[0, 0, 0]
    # Voxel centres inside a radius-5 ball: about 4/3 pi 5^3 = 524 of them.
    assert abs(int(grid.sum()) - 524) < 0.1 * 524


def test_disconnected_mesh_keeps_the_largest_part(tmp_path, caplog):
    big = trimesh.creation.box(extents=[2, 2, 2])
    small = trimesh.creation.box(extents=[1, 1, 1])
    small.apply_translation([5, 0, 0])
    trimesh.util.concatenate([big, small]).export(tmp_path / "two.obj")
    with caplog.at_level(logging.WARNING, logger="rllock.core.meshes"):
        grid = load_shape(str(tmp_path / "two.obj"), resolution=13)
    # Pitch 0.5: the big box is 4x4x4 voxels, the small one 2x2x2.
    assert grid.shape == (4, 4, 4) and grid.all()
    assert "dropped 8 of 72 voxels" in caplog.text


def test_a_mesh_that_falls_apart_is_refused_with_a_resolution_that_keeps_it(tmp_path):
    # Two cubes joined by a thin bar off their centre line: at resolution 4 no voxel centre lies in it.
    left, right = trimesh.creation.box(extents=[2, 2, 2]), trimesh.creation.box(extents=[2, 2, 2])
    right.apply_translation([4, 0, 0])
    bar = trimesh.creation.box(extents=[2.2, 0.4, 0.4])
    bar.apply_translation([2, 0.5, 0.5])
    solid = trimesh.boolean.union([left, bar, right], engine="manifold")
    solid.export(tmp_path / "dumbbell.stl")
    with pytest.raises(RLLockError, match=r"falls apart: its largest connected part keeps \d+ of \d+ voxels"):
        load_shape(str(tmp_path / "dumbbell.stl"), resolution=4)
    with pytest.raises(RLLockError) as refused:
        load_shape(str(tmp_path / "dumbbell.stl"), resolution=4)
    higher = int(str(refused.value).split("--resolution ")[1].split()[0])
    grid = load_shape(str(tmp_path / "dumbbell.stl"), resolution=higher)  # no error: one part now
    assert grid.sum() > 0 and higher > 4
    two = trimesh.util.concatenate([left, right])  # never joined
    two.export(tmp_path / "two_cubes.stl")
    with pytest.raises(RLLockError, match="no resolution up to 12 keeps them together"):
        load_shape(str(tmp_path / "two_cubes.stl"), resolution=6)


@pytest.mark.parametrize(
    "make,needle",
    [
        (
            lambda p: trimesh.Trimesh(
                trimesh.creation.box().vertices, trimesh.creation.box().faces[:-2]
            ).export(p / "open.stl"),
            "not watertight",
        ),
        (lambda p: (p / "junk.stl").write_text("this is no mesh"), "no triangle mesh"),
        (lambda p: (p / "empty.obj").write_text(""), "no triangle mesh"),
    ],
)
def test_bad_meshes_are_clear_errors(tmp_path, make, needle):
    make(tmp_path)
    (path,) = [p for p in tmp_path.iterdir()]
    with pytest.raises(RLLockError, match=needle):
        load_shape(str(path), resolution=4)


def test_resolution_is_checked(tmp_path):
    trimesh.creation.box().export(tmp_path / "box.stl")
    with pytest.raises(RLLockError, match="at least 1"):
        load_shape(str(tmp_path / "box.stl"), resolution=0)
    with pytest.raises(RLLockError, match="only to .stl and .obj"):
        load_shape("cube3", resolution=4)
    with pytest.raises(RLLockError, match="no such file"):
        load_shape(str(tmp_path / "missing.stl"))


def test_block_mesh_merges_coplanar_faces():
    mesh = piece_mesh(np.argwhere(np.ones((3, 3, 3), dtype=bool)), voxel_size=10)
    assert mesh.is_watertight
    assert len(mesh.faces) == 12  # two triangles per side of the cube
    assert mesh.volume == pytest.approx(27000)
    np.testing.assert_allclose(mesh.bounds, [[0, 0, 0], [30, 30, 30]])


def test_edge_touching_voxels_still_give_a_closed_mesh(tmp_path):
    # (0,0,0) and (1,1,0) meet only along an edge; the piece is connected through the layer above.
    cells = np.array([(0, 0, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (1, 1, 0)])
    mesh = piece_mesh(cells, voxel_size=1)
    assert mesh.is_watertight and mesh.volume == pytest.approx(5)
    mesh.export(tmp_path / "pinch.obj")
    assert trimesh.load(tmp_path / "pinch.obj", process=False).is_watertight
    # A gap separates the two sheets, so even a position-welded STL is closed.
    piece_mesh(cells, voxel_size=1, gap=0.1).export(tmp_path / "pinch.stl")
    assert trimesh.load(tmp_path / "pinch.stl").is_watertight
    assert edge_only_contacts(cells) == 1


def test_every_piece_of_a_2x2x2_block_welds_watertight_with_a_gap(tmp_path):
    """All 255 non-empty voxel sets of a 2x2x2 block, as one piece each: they hold every way voxels can
    meet (faces, edges only, corners only). With a gap the welded STL is closed and its volume is
    the documented formula; at gap 0 an STL can only open where voxels touch along an edge alone."""
    size, gap = 10.0, 0.2
    block = list(itertools.product((0, 1), repeat=3))
    pinched = 0
    for mask in range(1, 256):
        cells = np.array([v for i, v in enumerate(block) if mask >> i & 1])
        piece_mesh(cells, size, gap).export(tmp_path / "p.stl")
        welded = trimesh.load(tmp_path / "p.stl")
        assert welded.is_watertight, cells.tolist()
        assert welded.volume == pytest.approx(piece_volume(cells, size, gap), rel=1e-6)
        piece_mesh(cells, size).export(tmp_path / "exact.stl")
        exact = trimesh.load(tmp_path / "exact.stl")
        assert piece_volume(cells, size) == len(cells) * size**3
        assert exact.volume == pytest.approx(len(cells) * size**3)
        if edge_only_contacts(cells) == 0:
            assert exact.is_watertight, cells.tolist()
        pinched += edge_only_contacts(cells) > 0
    assert pinched > 50  # the edge-only case is well covered, not just present


def test_piece_volume_counts_cores_slabs_prisms_and_corners():
    r2 = 0.4  # 2r for a gap of 0.4 with unit voxels
    # A 2x2x2 block: 8 cores, 12 face pairs, 6 full squares, 1 full cube: one box of side 2 - 2r.
    cube = np.argwhere(np.ones((2, 2, 2), dtype=bool))
    assert piece_volume(cube, 1.0, 0.4) == pytest.approx((2 - r2) ** 3)
    # Two voxels on a diagonal share no face: two separate shrunken cubes.
    assert piece_volume(np.array([(0, 0, 0), (1, 1, 0)]), 1.0, 0.4) == pytest.approx(2 * (1 - r2) ** 3)
    assert piece_volume(cube, 10.0) == 8000


@pytest.fixture(scope="module")
def assembly() -> np.ndarray:
    from rllock.core.env import make_task
    from rllock.search.solver import search

    return next(search(make_task("cube4", 7), seed=0, time_limit=30)).labels


def test_pieces_fill_the_shape_without_overlap(assembly):
    meshes = assembly_meshes(assembly, voxel_size=10)
    assert all(m.is_watertight for m in meshes)
    for k, mesh in enumerate(meshes, start=1):
        assert mesh.volume == pytest.approx(int((assembly == k).sum()) * 1000)
    assert sum(m.volume for m in meshes) == pytest.approx(64 * 1000)
    solids = [_manifold(m) for m in meshes]
    for a, b in itertools.combinations(solids, 2):
        assert (a ^ b).volume() == pytest.approx(0, abs=1e-6)


def test_gap_shrinks_pieces_and_keeps_them_apart(assembly):
    size, gap = 10.0, 0.5
    meshes = assembly_meshes(assembly, voxel_size=size, gap=gap)
    for k, mesh in enumerate(meshes, start=1):
        cells = np.argwhere(assembly == k)
        assert mesh.is_watertight
        assert mesh.volume == pytest.approx(piece_volume(cells, size, gap), rel=1e-9)
        assert mesh.volume < len(cells) * size**3
        np.testing.assert_allclose(
            mesh.bounds,
            [cells.min(axis=0) * size + gap / 2, (cells.max(axis=0) + 1) * size - gap / 2],
            atol=1e-6,
        )
    solids = [_manifold(m) for m in meshes]
    touching = _face_neighbours(assembly)
    for (i, a), (j, b) in itertools.combinations(enumerate(solids, start=1), 2):
        assert (a ^ b).volume() == pytest.approx(0, abs=1e-9)
        # Pieces that shared a face end exactly `gap` apart, and no two pieces come closer.
        distance = a.min_gap(b, 2 * gap)
        assert distance >= gap - 1e-6
        if (i, j) in touching:
            assert distance == pytest.approx(gap, abs=1e-6)


def test_bad_sizes_are_clear_errors():
    cells = np.array([(0, 0, 0)])
    with pytest.raises(RLLockError, match="voxel size"):
        piece_mesh(cells, voxel_size=0)
    with pytest.raises(RLLockError, match="gap"):
        piece_mesh(cells, voxel_size=10, gap=10)
