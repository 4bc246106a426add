"""Mesh formats in: PLY (binary, ASCII, triangle strips), OFF, glTF/GLB and 3MF give the voxels the same
model gives as STL; a point cloud, an empty or a damaged file is one line and exit 2."""

from __future__ import annotations

import struct
import zipfile

import numpy as np
import pytest
import trimesh
from helpers import run_cli

from rllock.core.mesh_files import strip_faces
from rllock.core.meshes import voxelize_mesh

RESOLUTION = 8
TURN = np.array([[0.0, -1.0, 0.0, 5.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
"""A quarter turn about z, then a shift: x' = 5 - y, y' = x."""


def _model() -> trimesh.Trimesh:
    """A block with a post on one corner: no symmetry that a mirrored or wrongly turned file would keep."""
    block = trimesh.creation.box(bounds=[[0, 0, 0], [4, 3, 2]])
    post = trimesh.creation.box(bounds=[[0, 0, 2], [1, 1, 4]])
    return trimesh.boolean.union([block, post], engine="manifold")


def _reference(tmp_path, mesh: trimesh.Trimesh, name: str = "reference.stl") -> np.ndarray:
    mesh.export(tmp_path / name)
    return voxelize_mesh(tmp_path / name, RESOLUTION)


def _ply_strips(path, vertices: np.ndarray, strips: list[list[int]], binary: bool) -> None:
    """A PLY file whose surface is an element `tristrips` of one row: the strips, -1 between them."""
    row = [i for strip in strips for i in [*strip, -1]]
    header = (
        f"ply\nformat {'binary_little_endian' if binary else 'ascii'} 1.0\nelement vertex {len(vertices)}\n"
        "property float x\nproperty float y\nproperty float z\nelement tristrips 1\n"
        "property list int int vertex_indices\nend_header\n"
    )
    if binary:
        body = np.asarray(vertices, "<f4").tobytes() + struct.pack(f"<i{len(row)}i", len(row), *row)
        path.write_bytes(header.encode() + body)
    else:
        lines = [" ".join(map(str, v)) for v in vertices] + [" ".join(map(str, [len(row), *row]))]
        path.write_text(header + "\n".join(lines) + "\n")


def _3mf(path, parts: dict[str, str], items: str) -> None:
    """A 3MF package: the root model's resources (parts['3D/3dmodel.model']) and build `items`, and other
    model files (the production extension's parts)."""
    core = "http://schemas.microsoft.com/3dmanufacturing/core/2015/02"
    production = "http://schemas.microsoft.com/3dmanufacturing/production/2015/06"

    def model(resources: str, build: str = "") -> str:
        return (
            f'<?xml version="1.0" encoding="UTF-8"?>\n<model unit="millimeter" xmlns="{core}" '
            f'xmlns:p="{production}"><resources>{resources}</resources><build>{build}</build></model>'
        )

    with zipfile.ZipFile(path, "w") as z:
        z.writestr("[Content_Types].xml", '<?xml version="1.0"?><Types/>')
        z.writestr("_rels/.rels", '<?xml version="1.0"?><Relationships/>')
        for name, resources in parts.items():
            z.writestr(name, model(resources, items if name == "3D/3dmodel.model" else ""))


def _object(object_id: int, mesh: trimesh.Trimesh) -> str:
    vertices = "".join(f'<vertex x="{x}" y="{y}" z="{z}"/>' for x, y, z in mesh.vertices)
    triangles = "".join(f'<triangle v1="{a}" v2="{b}" v3="{c}"/>' for a, b, c in mesh.faces)
    body = f"<mesh><vertices>{vertices}</vertices><triangles>{triangles}</triangles></mesh>"
    return f'<object id="{object_id}" type="model">{body}</object>'


def _holder(object_id: int, component: str) -> str:
    """An object made of one component: `component` holds its attributes (objectid, transform, p:path)."""
    return f'<object id="{object_id}" type="model"><components><component {component}/></components></object>'


def _transform(matrix: np.ndarray) -> str:
    """A column-vector 4x4 matrix as 3MF writes it: the 4x3 matrix that acts on row vectors, row by row."""
    return " ".join(f"{v:g}" for v in matrix[:3, :].T.ravel())


def test_strips_make_triangles_turning_every_second_and_dropping_the_joins():
    rows = {"vertex_indices": np.array([[0, 1, 2, 3, -1, 4, 5, 6, 6, 7, 8]])}
    faces = strip_faces({"tristrips": {"length": 1, "data": rows}})
    # 0 1 2 3: (0 1 2), then (2 1 3) turned over; 4 5 6 6 7 8: the repeated 6 joins two strips.
    assert faces.tolist() == [[0, 1, 2], [2, 1, 3], [4, 5, 6], [7, 6, 8]]
    assert strip_faces({}).shape == (0, 3)


@pytest.mark.parametrize("kind", ["ply-binary", "ply-ascii", "off", "glb", "gltf"])
def test_a_format_gives_the_voxels_of_the_same_model_as_stl(tmp_path, kind):
    mesh = _model()
    want = _reference(tmp_path, mesh)
    path = tmp_path / f"model.{kind.split('-')[0]}"
    if kind == "ply-ascii":
        path.write_bytes(trimesh.exchange.ply.export_ply(mesh, encoding="ascii"))
    elif kind == "gltf":  # one self-contained file: the buffers inside it
        path.write_bytes(trimesh.Scene(mesh).export(file_type="gltf", embed_buffers=True)["model.gltf"])
    else:
        mesh.export(path)
    np.testing.assert_array_equal(voxelize_mesh(path, RESOLUTION), want)


@pytest.mark.parametrize("binary", [True, False])
def test_a_ply_of_triangle_strips_gives_the_voxels_of_its_triangles(tmp_path, binary):
    mesh = _model()
    want = _reference(tmp_path, mesh)
    # Each triangle a strip of its own, and the whole surface again as strips of two triangles: a
    # triangle (a, b, c) then (c, b, d) share the edge b-c and make the strip a b c d.
    path = tmp_path / "strips.ply"
    _ply_strips(path, mesh.vertices, [list(f) for f in mesh.faces], binary)
    np.testing.assert_array_equal(voxelize_mesh(path, RESOLUTION), want)
    box = trimesh.creation.box(bounds=[[0, 0, 0], [3, 2, 1]])
    corners = np.array([[x, y, z] for x in (0, 3) for y in (0, 2) for z in (0, 1)], float)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    _ply_strips(path, corners, [[a, b, d, c] for a, b, c, d in quads], binary)  # the box's faces, outward
    np.testing.assert_array_equal(voxelize_mesh(path, RESOLUTION), _reference(tmp_path, box, "box.stl"))


def test_a_3mf_places_its_build_items_and_components_in_other_model_files(tmp_path):
    mesh = _model()
    want = _reference(tmp_path, mesh.copy().apply_transform(TURN))
    assert not np.array_equal(want, _reference(tmp_path, mesh.copy().apply_transform(np.linalg.inv(TURN))))
    # The mesh as object 1; object 2 holds it as a component, shifted; the build places object 2 turned.
    shift = np.eye(4)
    shift[:3, 3] = [1.0, 2.0, 3.0]
    moved = mesh.copy().apply_transform(np.linalg.inv(shift))  # the component's shift puts it back
    item = f'<item objectid="2" transform="{_transform(TURN)}"/>'
    path = tmp_path / "model.3mf"
    holder = _holder(2, f'objectid="1" transform="{_transform(shift)}"')
    _3mf(path, {"3D/3dmodel.model": _object(1, moved) + holder}, item)
    np.testing.assert_array_equal(voxelize_mesh(path, RESOLUTION), want)
    # A slicer's package: the mesh in a model file of its own, which the root's component names by path.
    holder = _holder(2, 'p:path="/3D/Objects/part.model" objectid="1"')
    _3mf(path, {"3D/3dmodel.model": holder, "3D/Objects/part.model": _object(1, mesh)}, item)
    np.testing.assert_array_equal(voxelize_mesh(path, RESOLUTION), want)


def test_points_an_empty_or_a_damaged_file_are_one_line_and_exit_2(tmp_path):
    cloud = tmp_path / "scan.ply"
    trimesh.PointCloud(np.random.default_rng(0).random((50, 3))).export(cloud)
    glb = tmp_path / "broken.glb"
    _model().export(glb)
    glb.write_bytes(glb.read_bytes()[:200])
    (tmp_path / "empty.off").write_text("")
    (tmp_path / "notazip.3mf").write_text("solid nothing")
    empty = tmp_path / "nothing.3mf"
    _3mf(empty, {"3D/3dmodel.model": ""}, "")
    cases = {cloud: "point cloud", glb: "cannot read mesh", tmp_path / "empty.off": "empty.off",
             tmp_path / "notazip.3mf": "cannot read mesh", empty: "holds no triangle mesh"}  # fmt: skip
    for path, words in cases.items():
        code, _, err = run_cli("solve", "--shape", str(path), "--pieces", "3", "--out", str(tmp_path / "o"))
        assert code == 2 and words in err and len(err.strip().splitlines()) == 1, (path, err)
        assert "Traceback" not in err
