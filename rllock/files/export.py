"""Export an assembly for making or studying it: a mesh per piece (OBJ or STL), or a BurrTools puzzle.

Meshes (see `rllock.core.piece_meshes`): one watertight file per piece, `piece_01.stl` ... `piece_KK.stl` (or
`.obj`), in millimetres, each in its assembled position (voxel (x, y, z) spans [x, x+1] * voxel size
along x, and so on), so loading them all shows the assembled shape. With a clearance gap every piece
is shrunk by gap/2 on each face that borders another piece or the outside, leaving `gap` between
neighbouring pieces. The gap defaults to PRINT_GAP = 0.2 mm, a typical FDM printing clearance, which also
keeps every STL file watertight when a slicer welds its vertices (at gap 0, voxels of one piece that touch
only along an edge make a non-manifold edge there: see `rllock.core.piece_meshes`). Gap 0 gives the
exact shape. Exporting into a folder that holds an earlier export replaces that export: piece files of the
same format that this one does not write (an earlier, larger puzzle's `piece_07.stl` ...) are removed and
named in the log, so the folder holds exactly this puzzle's pieces; nothing else in the folder is touched.

BurrTools (`.xmpuzzle`, gzip-compressed XML, puzzle format version 2, the brick grid):
  axes          identity: BurrTools' x, y, z are the label grid's x, y, z, and a shape's voxel string
                lists its voxels x fastest, then y, then z, as `.puz` does ('#' filled, '_' empty)
  shapes        shape 0 is the assembled shape (the problem's result); shape i (1..K) is piece i,
                cropped to its bounding box
  problem       uses shapes 1..K once each, so BurrTools' piece i-1 is RL-Lock's piece i and the key is
                its first piece; it is marked unsolved, so BurrTools' own solver can search it afresh
  solution      the assembly places every piece unrotated (orientation 0) at its bounding box's lower
                corner in the result; the separation tree takes the pieces out in RL-Lock's order, one
                per level: each level lists the pieces still there, a state per verified move (offsets
                from the assembled position), and a last state that sends the moving piece 20000 units
                along its final direction, which is how BurrTools marks a piece as removed
"""

from __future__ import annotations

import gzip
import logging
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from rllock.core.reference_checkers import DIRECTION_NAMES, DIRECTIONS
from rllock.core.shapes import to_xfastest
from rllock.core.verifier import Verdict, validate_labels
from rllock.errors import RLLockError

MESH_FORMATS = ("obj", "stl")
FORMATS = (*MESH_FORMATS, "xmpuzzle")
# BurrTools takes any offset beyond 10000 units as "removed"; its own disassembler writes 20000.
_REMOVED = 20000
# Millimetres between neighbouring pieces by default: what FDM printers need for printed pieces to fit,
# and enough to part voxels of one piece that touch only along an edge, so STL files weld watertight.
PRINT_GAP = 0.2

log = logging.getLogger(__name__)


def write_meshes(
    labels: np.ndarray, fmt: str, out_dir: str | Path, voxel_size: float = 10.0, gap: float = PRINT_GAP
) -> list[Path]:
    """One mesh file per piece, `piece_NN.<fmt>`, in piece order; returns the paths written. Earlier
    `piece_NN.<fmt>` files in `out_dir` that this export does not replace are removed (module docstring)."""
    from rllock.core.piece_meshes import (  # imported here: trimesh is slow to import
        assembly_meshes,
        edge_only_contacts,
    )

    if fmt not in MESH_FORMATS:
        raise RLLockError(f"unknown mesh format {fmt!r}: use one of {', '.join(MESH_FORMATS)}")
    k = validate_labels(labels)
    if fmt == "stl" and gap == 0:
        pinched = [i for i in range(1, k + 1) if edge_only_contacts(np.argwhere(labels == i))]
        if pinched:
            ids = ", ".join(map(str, pinched))
            which = f"piece {ids} has" if len(pinched) == 1 else f"pieces {ids} have"
            log.warning(
                "%s voxels that touch only along an edge: with gap 0 such STL files are not manifold "
                "once a slicer welds vertices (use a gap > 0, or OBJ)",
                which,
            )
    meshes = assembly_meshes(labels, voxel_size, gap)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    width = max(2, len(str(len(meshes))))
    paths = []
    for i, mesh in enumerate(meshes, start=1):
        path = out / f"piece_{i:0{width}d}.{fmt}"
        mesh.export(path)
        paths.append(path)
    _remove_stale_pieces(out, fmt, paths)
    return paths


def _remove_stale_pieces(out: Path, fmt: str, written: list[Path]) -> None:
    """Remove the piece files of an earlier export into `out` that `written` did not replace: left
    there, a slicer or viewer loading the folder would mix another puzzle's pieces into this one."""
    pattern = re.compile(rf"piece_[0-9]{{2,}}\.{fmt}")
    keep = {p.name for p in written}
    stale = sorted(
        (p for p in out.iterdir() if pattern.fullmatch(p.name) and p.name not in keep and p.is_file()),
        key=lambda p: (len(p.name), p.name),  # piece order: piece_100 after piece_20
    )
    for path in stale:
        path.unlink()
    if stale:
        log.info(
            "removed %d piece %s of an earlier export from %s: %s",
            len(stale),
            "file" if len(stale) == 1 else "files",
            out,
            ", ".join(p.name for p in stale),
        )


# Where the separations' text goes in the document (`_separations`).
_SEPARATIONS = "rllock-separations"


def _voxel(grid: np.ndarray, name: str) -> ET.Element:
    x, y, z = grid.shape
    element = ET.Element("voxel", x=str(x), y=str(y), z=str(z), name=name, type="0")
    element.text = "".join("#" if v else "_" for v in to_xfastest(grid))
    return element


def _numbers(tag: str, values) -> ET.Element:
    element = ET.Element(tag)
    element.text = " ".join(str(int(v)) for v in values)
    return element


def _state(offsets: np.ndarray) -> ET.Element:
    state = ET.Element("state")
    for axis, tag in enumerate(("dx", "dy", "dz")):
        state.append(_numbers(tag, offsets[:, axis]))
    return state


def _separations(disassembly: list[dict], k: int) -> str:
    """The solution's separations as XML text: the one that takes piece `level + 1` out of pieces
    level+1..K (0-based indices level..K-1) holds the rest's separation as its "left" part, K - 1 levels
    deep. Written as text, level by level, because ElementTree serializes nested elements recursively,
    beyond Python's recursion limit at about a thousand pieces."""
    opened = []
    for level in range(k - 1):
        pieces = list(range(level, k))
        element = ET.Element("separation")
        if level > 0:
            element.set("type", "left")
        pieces_el = _numbers("pieces", pieces)
        pieces_el.set("count", str(len(pieces)))
        element.append(pieces_el)
        offsets = np.zeros((len(pieces), 3), dtype=int)
        element.append(_state(offsets))
        moves = disassembly[level]["moves"]
        for n, move in enumerate(moves):
            vec = np.asarray(DIRECTIONS[DIRECTION_NAMES.index(move["direction"])])
            # The last move already clears the other pieces, so it becomes the move to "infinity".
            offsets[0] += vec * (_REMOVED if n == len(moves) - 1 else move["steps"])
            element.append(_state(offsets))
        text = ET.tostring(element, encoding="unicode")
        opened.append(text.removesuffix("</separation>"))
    return "".join(opened) + "</separation>" * len(opened)


def xmpuzzle_xml(labels: np.ndarray, verdict: Verdict, title: str) -> str:
    """The BurrTools document (uncompressed) for a valid assembly and its verdict."""
    if not verdict.valid:
        raise RLLockError("only a valid assembly can be exported to BurrTools")
    k = validate_labels(labels)
    puzzle = ET.Element("puzzle", version="2")
    ET.SubElement(puzzle, "gridType", type="0")
    shapes = ET.SubElement(puzzle, "shapes")
    shapes.append(_voxel(labels != 0, "assembly"))
    corners = []
    for i in range(1, k + 1):
        cells = np.argwhere(labels == i)
        lo, hi = cells.min(axis=0), cells.max(axis=0) + 1
        corners.append(lo)
        box = labels[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]] == i
        shapes.append(_voxel(box, f"P{i} (key)" if i == 1 else f"P{i}"))
    problem = ET.SubElement(ET.SubElement(puzzle, "problems"), "problem", name=title, state="0")
    parts = ET.SubElement(problem, "shapes")
    for i in range(1, k + 1):
        ET.SubElement(parts, "shape", id=str(i), count="1")
    ET.SubElement(problem, "result", id="0")
    solution = ET.SubElement(ET.SubElement(problem, "solutions"), "solution")
    assembly = ET.SubElement(solution, "assembly")
    assembly.text = " ".join(f"{x} {y} {z} 0" for x, y, z in corners)
    ET.SubElement(solution, _SEPARATIONS)
    comment = ET.SubElement(puzzle, "comment")
    comment.text = (
        f"{title}: made by RL-Lock, {k} pieces, removal={verdict.removal}; piece P1 is the key, "
        f"pieces come out in the order P1..P{k - 1}, P{k} stays"
    )
    # BurrTools' parser wants its own plain declaration; the body has no whitespace between tags.
    body = ET.tostring(puzzle, encoding="unicode")
    return '<?xml version="1.0"?>\n' + body.replace(
        f"<{_SEPARATIONS} />", _separations(verdict.disassembly, k)
    )


def write_xmpuzzle(labels: np.ndarray, verdict: Verdict, path: str | Path, title: str) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with gzip.open(path, "wt", encoding="utf-8") as fh:
        fh.write(xmpuzzle_xml(labels, verdict, title))
    return path
