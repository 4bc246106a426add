"""Meshes both ways: .stl/.obj models to voxel shapes (open ones by winding numbers), voxel pieces to
watertight meshes."""

from __future__ import annotations

import itertools
import logging

import manifold3d as m3
import numpy as np
import pytest
import trimesh
from matplotlib.path import Path as MplPath
from scipy import ndimage

from rllock.core.meshes import _inside_rows, voxelize_mesh
from rllock.core.piece_meshes import assembly_meshes, edge_only_contacts, piece_mesh, piece_volume
from rllock.core.shapes import load_shape
from rllock.core.winding import build_tree, winding_numbers, winding_numbers_exact
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


def _frame(mesh: trimesh.Trimesh, shape: tuple[int, ...], resolution: int) -> tuple[np.ndarray, float]:
    """(lower corner, pitch) of a voxelized mesh's grid: centred on its bounding box, `resolution` voxels
    along its longest side."""
    lo, hi = mesh.bounds
    pitch = float((hi - lo).max()) / resolution
    return (lo + hi) / 2 - np.asarray(shape) * pitch / 2, pitch


def _shares(mesh: trimesh.Trimesh, grid: np.ndarray, resolution: int, cells: np.ndarray) -> np.ndarray:
    """The exact share of each cell's volume inside the mesh, from manifold3d's intersection of the solid
    with the cell's box."""
    origin, pitch = _frame(mesh, grid.shape, resolution)
    solid, box = _manifold(mesh), m3.Manifold.cube([pitch] * 3)
    corners = origin + np.asarray(cells, dtype=float).reshape(-1, 3) * pitch
    return np.array([(solid ^ box.translate(corner)).volume() / pitch**3 for corner in corners])


def _centres_inside(mesh: trimesh.Trimesh, shape: tuple[int, ...], resolution: int) -> np.ndarray:
    """The old rule, as a reference: voxel centres inside the mesh, each layer tested against the solid's
    cross-section by matplotlib. The centres are nudged as the module nudges them, so that near-ties
    fall the same way."""
    origin, pitch = _frame(mesh, shape, resolution)
    centres = [
        origin[a] + (np.arange(shape[a]) + 0.5 + 1e-4 * np.sqrt((2, 3, 5)[a])) * pitch for a in range(3)
    ]
    points = np.stack(np.meshgrid(centres[0], centres[1], indexing="ij"), axis=-1).reshape(-1, 2)
    grid = np.zeros(shape, dtype=bool)
    for iz, z in enumerate(centres[2]):
        inside = np.zeros(len(points), dtype=bool)
        for contour in _manifold(mesh).slice(z).to_polygons():
            inside ^= MplPath(contour).contains_points(points)
        grid[:, :, iz] = inside.reshape(shape[:2])
    return grid


def _parts(grid: np.ndarray) -> int:
    return int(ndimage.label(grid)[1])  # 6-connected


def test_box_mesh_voxelizes_to_a_full_box(tmp_path):
    trimesh.creation.box(extents=[4, 2, 1]).export(tmp_path / "box.stl")
    grid = load_shape(str(tmp_path / "box.stl"), resolution=4)
    assert grid.shape == (4, 2, 1) and grid.all()
    # Without a resolution the default (8 voxels along the longest side) applies.
    assert load_shape(str(tmp_path / "box.stl")).shape == (8, 4, 2)


def test_sphere_fills_its_inside(tmp_path):
    ball = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    ball.export(tmp_path / "ball.obj")
    grid = load_shape(str(tmp_path / "ball.obj"), resolution=10)
    assert grid.shape == (10, 10, 10)
    assert grid[5, 5, 5] and not grid[0, 0, 0]
    # Voxel centres inside a radius-5 ball: about 4/3 pi 5^3 = 524 of them.
    assert abs(int(grid.sum()) - 524) < 0.1 * 524
    # A convex model does not grow: exactly the voxels whose centre is inside the polyhedron, at every
    # resolution (the half rule and the bridges add nothing).
    for resolution in (7, 10, 13, 16):
        grid = voxelize_mesh(tmp_path / "ball.obj", resolution)
        origin, pitch = _frame(ball, grid.shape, resolution)
        centres = origin + (np.argwhere(np.ones(grid.shape, dtype=bool)) + 0.5) * pitch
        offsets = centres @ ball.face_normals.T - np.sum(ball.face_normals * ball.triangles[:, 0], axis=1)
        np.testing.assert_array_equal(grid.ravel(), (offsets < 0).all(axis=1))


def test_voxels_less_than_half_inside_stay_empty(tmp_path):
    # A 4-cube with a 1.3 x 1.3 post on top, at pitch 1: the post fills one column of voxels and 30% (or
    # 9%) of its neighbours, whose centres are outside: those stay empty.
    block = trimesh.creation.box(bounds=[[0, 0, 0], [4, 4, 4]])
    post = trimesh.creation.box(bounds=[[0, 0, 3.5], [1.3, 1.3, 6]])
    trimesh.boolean.union([block, post], engine="manifold").export(tmp_path / "post.stl")
    grid = load_shape(str(tmp_path / "post.stl"), resolution=6)
    assert grid.shape == (4, 4, 6) and grid[:, :, :4].all()
    np.testing.assert_array_equal(np.argwhere(grid[:, :, 4:]), [(0, 0, 0), (0, 0, 1)])


def test_a_slot_through_the_centres_keeps_the_voxels_it_cuts(tmp_path):
    # A slot 0.1 wide through the plane of centres x = 1.5, down to 0.3 above the bottom: the voxels it
    # cuts lose their centre but keep 90% of their volume or more. The centre rule alone split the block
    # in two, and a bridge would have added only one of them back.
    block = trimesh.creation.box(bounds=[[0, 0, 0], [4, 4, 2]])
    slot = trimesh.creation.box(bounds=[[1.45, -1, 0.3], [1.55, 5, 3]])
    solid = trimesh.boolean.difference([block, slot], engine="manifold")
    solid.export(tmp_path / "slot.stl")
    grid = voxelize_mesh(tmp_path / "slot.stl", 4)
    assert grid.shape == (4, 4, 2) and grid.all()
    assert not _centres_inside(solid, grid.shape, 4)[1].any()
    assert (_shares(solid, grid, 4, np.argwhere(grid)) > 0.5).all()


def test_boxes_that_meet_along_an_edge_are_bridged_into_one_shape(tmp_path, caplog):
    # Two slabs that overlap only in a 0.1 x 0.1 column at (1.85, 1.85). At pitch 0.8 the voxel centres
    # give a 2x2 and a 3x3 block that touch only along an edge: the old rule dropped the smaller one, and
    # so refused the mesh.
    a = trimesh.creation.box(bounds=[[0, 0, 0], [1.9, 1.9, 1]])
    b = trimesh.creation.box(bounds=[[1.8, 1.8, 0], [4, 4, 1]])
    solid = trimesh.boolean.union([a, b], engine="manifold")
    solid.export(tmp_path / "edge.stl")
    with caplog.at_level(logging.WARNING, logger="rllock.core.meshes"):
        grid = voxelize_mesh(tmp_path / "edge.stl", 5)
    assert not caplog.text
    assert grid.shape == (5, 5, 2) and _parts(grid) == 1
    centres = _centres_inside(solid, grid.shape, 5)
    assert _parts(centres) == 2 and (grid >= centres).all()
    assert grid[:2, :2].all() and grid[2:, 2:].all()
    # One voxel joins them, beside the edge, and holds some of the solid.
    (bridge,) = np.argwhere(grid & ~centres)
    assert tuple(bridge[:2]) in {(1, 2), (2, 1)}
    assert _shares(solid, grid, 5, [bridge])[0] > 0


def test_a_thin_bar_off_the_centres_is_kept(tmp_path, caplog):
    # Two cubes joined by a bar 0.4 thick off their centre line: at resolution 4 (pitch 1.5) no voxel
    # centre lies in it, so the old rule found two halves; the bar is now two voxels.
    left, right = trimesh.creation.box(extents=[2, 2, 2]), trimesh.creation.box(extents=[2, 2, 2])
    right.apply_translation([4, 0, 0])
    bar = trimesh.creation.box(extents=[2.2, 0.4, 0.4])
    bar.apply_translation([2, 0.5, 0.5])
    solid = trimesh.boolean.union([left, bar, right], engine="manifold")
    solid.export(tmp_path / "dumbbell.stl")
    with caplog.at_level(logging.WARNING, logger="rllock.core.meshes"):
        grid = voxelize_mesh(tmp_path / "dumbbell.stl", 4)
    assert not caplog.text
    centres = _centres_inside(solid, grid.shape, 4)
    assert _parts(centres) == 2 and _parts(grid) == 1 and (grid >= centres).all()
    added = np.argwhere(grid & ~centres)
    np.testing.assert_array_equal(added, [(1, 1, 1), (2, 1, 1)])  # where the bar runs
    assert (_shares(solid, grid, 4, added) > 0).all()


def _bunny_like() -> trimesh.Trimesh:
    """A body, a head and two slanted ears thinner than a voxel at the resolutions below."""
    body = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    body.apply_scale([1.2, 1.0, 0.9])
    head = trimesh.creation.icosphere(subdivisions=3, radius=0.55)
    head.apply_translation([1.1, 0, 0.75])
    ears = []
    for side in (-1, 1):
        ear = trimesh.creation.capsule(height=0.9, radius=0.1, count=[16, 16])
        ear.apply_transform(trimesh.transformations.rotation_matrix(np.radians(25 * side), [1, 0, 0]))
        ear.apply_transform(trimesh.transformations.rotation_matrix(np.radians(-20), [0, 1, 0]))
        ear.apply_translation([1.15, 0.2 * side, 1.55])
        ears.append(ear)
    return trimesh.boolean.union([body, head, *ears], engine="manifold")


def test_thin_slanted_ears_stay_on(tmp_path, caplog):
    model = _bunny_like()
    model.export(tmp_path / "bunny.stl")
    split = 0
    for resolution in range(7, 21):
        with caplog.at_level(logging.WARNING, logger="rllock.core.meshes"):
            grid = voxelize_mesh(tmp_path / "bunny.stl", resolution)
        assert not caplog.text, resolution
        centres = _centres_inside(model, grid.shape, resolution)
        split += _parts(centres) > 1
        assert _parts(grid) == 1 and (grid >= centres).all(), resolution
        # Every voxel the old rule lacked holds some of the solid: none is added in empty space.
        assert (_shares(model, grid, resolution, np.argwhere(grid & ~centres)) > 0).all(), resolution
    assert split >= 5  # the ears did fall off under the old rule
    np.testing.assert_array_equal(grid, voxelize_mesh(tmp_path / "bunny.stl", 20))


def test_disconnected_mesh_keeps_the_largest_part(tmp_path, caplog):
    big = trimesh.creation.box(extents=[2, 2, 2])
    small = trimesh.creation.box(extents=[1, 1, 1])
    small.apply_translation([5, 0, 0])
    trimesh.util.concatenate([big, small]).export(tmp_path / "two.obj")
    with caplog.at_level(logging.WARNING, logger="rllock.core.meshes"):
        grid = load_shape(str(tmp_path / "two.obj"), resolution=13)
    # Pitch 0.5: the big box is 4x4x4 voxels, the small one 2x2x2; nothing joins them.
    assert grid.shape == (4, 4, 4) and grid.all()
    assert "dropped 8 of 72 voxels; no resolution up to 26 keeps them together" in caplog.text


def _dumbbell(left: float, right: float, gap: float, bar: float, offset: float) -> trimesh.Trimesh:
    """Cubes of sides `left` and `right`, `gap` apart along x, joined by a bar `bar` thick whose lower
    edges are `offset` - bar/2 off the cubes' centre line along y and z."""
    a, b = trimesh.creation.box(extents=[left] * 3), trimesh.creation.box(extents=[right] * 3)
    a.apply_translation([left / 2, 0, 0])
    b.apply_translation([left + gap + right / 2, 0, 0])
    rod = trimesh.creation.box(extents=[gap + 0.2, bar, bar])
    rod.apply_translation([left + gap / 2, offset, offset])
    return trimesh.boolean.union([a, rod, b], engine="manifold")


def test_a_mesh_that_falls_apart_is_refused_with_a_resolution_that_keeps_it(tmp_path):
    # A bar 0.2 thick, at 0.2..0.4 off the centre line: at resolution 4 it falls between the sub-samples
    # (0.15 and 0.45), at resolution 5 one row of them (0.36) runs through it.
    _dumbbell(2, 2, 2, 0.2, 0.3).export(tmp_path / "dumbbell.stl")
    with pytest.raises(RLLockError) as refused:
        load_shape(str(tmp_path / "dumbbell.stl"), resolution=4)
    message = str(refused.value)
    assert "\n" not in message
    assert "falls apart: its largest connected part keeps 4 of 8 voxels; --resolution 5 keeps" in message
    grid = load_shape(str(tmp_path / "dumbbell.stl"), resolution=5)  # no error: one part now
    assert grid.shape == (5, 2, 2) and _parts(grid) == 1 and grid[2].any()
    # Without the bar, nothing joins them, though at pitch 1.5 the voxels either side of the 2-wide gap
    # each hold some of a cube: no sub-sample pair across the face between those voxels is inside.
    left, right = trimesh.creation.box(extents=[2, 2, 2]), trimesh.creation.box(extents=[2, 2, 2])
    right.apply_translation([4, 0, 0])
    trimesh.util.concatenate([left, right]).export(tmp_path / "two_cubes.stl")
    with pytest.raises(RLLockError, match="keeps 4 of 8 voxels; no resolution up to 8 keeps them together"):
        load_shape(str(tmp_path / "two_cubes.stl"), resolution=4)


def test_a_small_loose_part_is_dropped_with_a_warning_naming_a_resolution_that_keeps_it(tmp_path, caplog):
    _dumbbell(3, 1, 1.5, 0.15, 0.3).export(tmp_path / "lopsided.stl")
    with caplog.at_level(logging.WARNING, logger="rllock.core.meshes"):
        grid = load_shape(str(tmp_path / "lopsided.stl"), resolution=5)
    assert len(caplog.records) == 1
    assert "dropped 1 of 28 voxels; --resolution 6 keeps its parts together" in caplog.text
    assert _parts(grid) == 1 and grid.sum() == 27
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="rllock.core.meshes"):
        grid = load_shape(str(tmp_path / "lopsided.stl"), resolution=6)
    assert not caplog.text and _parts(grid) == 1


def test_rows_of_points_in_polygons_match_matplotlib():
    rng = np.random.default_rng(0)
    for _ in range(100):
        contours = []
        for radius, turn in ((1.0, 1), (0.4, -1)):  # an outline and a hole inside it, the other way round
            angles = np.sort(rng.uniform(0, 2 * np.pi, int(rng.integers(3, 30))))[::turn]
            r = radius * rng.uniform(0.5, 1, len(angles))
            contours.append(np.c_[r * np.cos(angles), r * np.sin(angles)])
        xs, ys = np.sort(rng.uniform(-1, 1, 37)), np.sort(rng.uniform(-1, 1, 41))
        points = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)
        expected = np.zeros(len(points), dtype=bool)
        for contour in contours:
            expected ^= MplPath(contour).contains_points(points)
        np.testing.assert_array_equal(_inside_rows(contours, xs, ys), expected.reshape(37, 41))


def _finned() -> trimesh.Trimesh:
    """A closed box with a fin on one edge: that edge has three faces, and the fin's open edges form no
    loop that a cap could close."""
    box = trimesh.creation.box()
    a, b = box.edges_unique[0]
    tip = len(box.vertices)
    faces = np.vstack([box.faces, [[a, b, tip]]])
    return trimesh.Trimesh(np.vstack([box.vertices, [[3.0, 3.0, 3.0]]]), faces)


def test_holes_in_a_scanned_surface_are_closed_with_flat_caps(tmp_path, caplog):
    box = trimesh.creation.box(extents=[4, 2, 2])
    top_and_bottom = np.abs(box.triangles_center[:, 2]) > 0.99
    open_box = trimesh.Trimesh(box.vertices, box.faces[~top_and_bottom], process=False)
    assert not open_box.is_watertight
    open_box.export(tmp_path / "open.stl")
    with caplog.at_level(logging.WARNING):
        grid = load_shape(str(tmp_path / "open.stl"), resolution=4)
    assert grid.shape == (4, 2, 2) and grid.all()  # each cap closes the box where its faces were
    assert "2 hole(s)" in caplog.text


def _holed_ball() -> trimesh.Trimesh:
    """An icosphere with one face in ten removed, scattered: holes that share vertices, which no flat
    cap closes."""
    ball = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    keep = np.random.default_rng(0).random(len(ball.faces)) > 0.1
    return trimesh.Trimesh(ball.vertices, ball.faces[keep], process=False)


def test_winding_numbers_of_the_cluster_tree_match_the_exact_sum():
    """The tree's dipole approximation against the sum over every triangle, for an open surface and for
    two overlapping spheres (self-intersecting), at points inside, outside and near the surface."""
    two = trimesh.util.concatenate(
        [trimesh.creation.icosphere(3, 1.0), trimesh.creation.icosphere(3, 0.8).apply_translation([1, 0, 0])]
    )
    rng = np.random.default_rng(1)
    for mesh in (_holed_ball(), two):
        points = rng.uniform(mesh.bounds[0] - 0.3, mesh.bounds[1] + 0.3, (400, 3))
        exact = winding_numbers_exact(mesh.vertices, mesh.faces, points)
        fast = winding_numbers(build_tree(mesh.vertices, mesh.faces), points)
        assert np.abs(fast - exact).max() < 0.02
        assert (exact > 0.5).sum() > 50 and (exact < 0.5).sum() > 50
    # Where the two spheres overlap the winding number is 2: still inside.
    assert winding_numbers(build_tree(two.vertices, two.faces), np.array([[0.6, 0, 0]]))[0] > 1.9


def test_meshes_that_are_not_closed_fill_where_their_winding_number_is_above_a_half(tmp_path, caplog):
    ball = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    ball.export(tmp_path / "ball.obj")
    _holed_ball().export(tmp_path / "holed.obj")
    with caplog.at_level(logging.WARNING):
        holed = load_shape(str(tmp_path / "holed.obj"), resolution=10)
    assert "open edges): inside and outside decided by winding numbers" in caplog.text
    closed = load_shape(str(tmp_path / "ball.obj"), resolution=10)
    assert holed.shape == closed.shape and (holed != closed).sum() <= 0.03 * closed.sum()
    # A fin on a closed box (an edge of three faces, a sheet with open edges) fills nothing: the model
    # spans -0.5..3 along each axis, so at resolution 7 the unit box is exactly 2^3 voxels (and the shape
    # is cropped to its voxels).
    _finned().export(tmp_path / "fin.stl")
    fin = load_shape(str(tmp_path / "fin.stl"), resolution=7)
    assert fin.shape == (2, 2, 2) and fin.all()


def _two_sheets() -> trimesh.Trimesh:
    """Two flat squares at right angles that share one corner: not flat as a whole, open edges that no cap
    closes (two loops through one vertex), and nothing enclosed."""
    vertices = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (2, 1, 0), (2, 1, 1), (1, 1, 1)]
    faces = [(0, 1, 2), (0, 2, 3), (2, 4, 5), (2, 5, 6)]
    return trimesh.Trimesh(np.array(vertices, float), np.array(faces), process=False)


@pytest.mark.parametrize(
    "make,needle",
    [
        (
            lambda p: _two_sheets().export(p / "sheets.stl"),
            "has no inside: its open surface encloses no voxel",
        ),
        (lambda p: trimesh.creation.box([2, 2, 0]).export(p / "flat.obj"), "is flat"),
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
    with pytest.raises(RLLockError, match=r"only to meshes \(STL, OBJ, PLY, OFF, GLB, GLTF, 3MF\)"):
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


def test_a_textured_obj_split_along_its_seams_is_merged_by_position(tmp_path):
    """Textured models repeat a vertex wherever its texture coordinates change (each face of this box has
    its own four), so by index the surface is open along every seam; by position it is closed."""
    box = trimesh.creation.box(extents=[4, 2, 2])
    lines, faces = [], []
    for f, (a, b, c) in enumerate(box.faces):
        for i, v in enumerate((a, b, c)):
            lines.append("v {} {} {}".format(*box.vertices[v]))
            lines.append(f"vt {i / 2} {f / len(box.faces)}")
        faces.append(f"f {3 * f + 1}/{3 * f + 1} {3 * f + 2}/{3 * f + 2} {3 * f + 3}/{3 * f + 3}")
    (tmp_path / "textured.obj").write_text("\n".join(lines + faces) + "\n")
    grid = load_shape(str(tmp_path / "textured.obj"), resolution=4)
    assert grid.shape == (4, 2, 2) and grid.all()


def test_meshes_made_in_worker_processes_equal_those_made_in_this_one(assembly):
    one = assembly_meshes(assembly, voxel_size=10, gap=0.4, workers=1)
    two = assembly_meshes(assembly, voxel_size=10, gap=0.4, workers=2)
    assert len(one) == len(two) == 7
    for a, b in zip(one, two):
        np.testing.assert_array_equal(a.vertices, b.vertices)
        np.testing.assert_array_equal(a.faces, b.faces)


def _eroded_by_boxes(cells: np.ndarray, size: float, gap: float) -> m3.Manifold:
    """The eroded piece as the plain union of boxes: each voxel's core, and a bridge to every neighbour,
    every full 2x2 square and every full 2x2x2 cube it belongs to (the reference for the refined grid)."""
    filled = {tuple(int(c) for c in v) for v in cells}
    inset = gap / 2 / size
    boxes = []
    for v in filled:
        for off in itertools.product((0, 1), repeat=3):
            block = itertools.product(*[range(v[a], v[a] + 1 + off[a]) for a in range(3)])
            if all(b in filled for b in block):
                lo = (np.asarray(v, dtype=float) + inset) * size
                hi = (np.asarray(v, dtype=float) + 1 - inset + np.asarray(off)) * size
                boxes.append(m3.Manifold.cube(hi - lo).translate(lo))
    return m3.Manifold.batch_boolean(boxes, m3.OpType.Add)


def test_eroded_pieces_equal_the_union_of_boxes_on_random_pieces():
    """Random pieces in a 4^3 box, many with voxels that meet only along an edge or at a corner: the
    surface built from the refined grid is a closed 2-manifold that encloses exactly the boxes' union."""
    rng = np.random.default_rng(5)
    edge_or_corner = 0
    for _ in range(40):
        cells = np.unique(rng.integers(0, 4, (int(rng.integers(2, 14)), 3)), axis=0)
        edge_or_corner += edge_only_contacts(cells) > 0
        mesh = piece_mesh(cells, voxel_size=10, gap=0.6)
        assert mesh.is_watertight
        assert mesh.volume == pytest.approx(piece_volume(cells, 10, 0.6), rel=1e-6)
        reference = _eroded_by_boxes(cells, 10, 0.6)
        assert (_manifold(mesh) ^ reference).volume() == pytest.approx(reference.volume(), rel=1e-5)
    assert edge_or_corner >= 10
