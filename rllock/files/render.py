"""Pictures of an assembly: a PNG (assembled and exploded), an animated GIF and an interactive HTML page.

All of them take the label grid [x, y, z] (0 empty, 1..K the piece ids = removal order, 1 = the key) and
give every piece the same colour. The GIF and the HTML page follow the verifier's disassembly
(`Verdict.disassembly`): piece 1 (the key) first, each piece along its verified moves out of the
remaining pieces' bounding box, piece K staying put. Matplotlib draws through its Agg canvas directly
(no pyplot), so nothing here changes the process-wide backend.
"""

from __future__ import annotations

import base64
import colorsys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from mpl_toolkits.mplot3d import Axes3D
from mpl_toolkits.mplot3d.art3d import Poly3DCollection
from PIL import Image

from rllock.core.reference_checkers import DIRECTION_NAMES, DIRECTIONS
from rllock.core.verifier import Verdict, contact_pairs, validate_labels

# Flat shading by face direction (+x, -x, +y, -y, +z, -z): enough to read the shape without a light model.
_SHADE = (0.82, 0.62, 0.72, 0.9, 1.0, 0.55)
# The exploded view numbers every piece up to this many; beyond, numbers would cover the pieces, and only
# the key is marked.
MAX_NUMBERED = 60
# The GIF and the HTML page show every piece in every step of the disassembly, so they grow with the
# square of K ; beyond this many pieces they
# would take hours and gigabytes, and only the PNG is drawn.
MAX_ANIMATED = 200
# GIF frames: at most this many per move, however many unit steps the move has.
_FRAMES_PER_MOVE = 3
# The PNG's camera, in degrees.
_ELEV, _AZIM = 24.0, -58.0
# A label goes on the nearest of a piece's faces that face the camera and are not hidden; the ray test
# that tells hidden ones looks at this many candidates, nearest first.
_LABEL_CANDIDATES = 64


# Up to this many pieces each gets a colour of its own; more share DISTINCT colours so that no two touching
# pieces do (`piece_colors`): hundreds of hues cannot be told apart, a few dozen can.
DISTINCT = 24


def _golden_colors(k: int) -> np.ndarray:
    """K distinct RGB colours in [0, 1]: hues spaced by the golden ratio, alternating in brightness,
    so that neighbours in the removal order never look alike; the first is red."""
    colors = []
    for i in range(k):
        hue = (i * 0.618033988749895) % 1.0
        sat, val = ((0.75, 0.95), (0.55, 0.8), (0.9, 0.7))[i % 3]
        colors.append(colorsys.hsv_to_rgb(hue, sat, val))
    return np.asarray(colors)


def touching_pieces(labels: np.ndarray) -> list[set[int]]:
    """For each piece 1..K (index 0..K-1), the pieces whose voxels share a face with its voxels."""
    out: list[set[int]] = [set() for _ in range(int(labels.max()))]
    for pairs in contact_pairs(labels):
        for i, j in pairs.tolist():
            out[i - 1].add(j - 1)
            out[j - 1].add(i - 1)
    return out


def piece_colors(labels: np.ndarray) -> np.ndarray:
    """An RGB colour in [0, 1] per piece 1..K of a label grid, the key red. Up to DISTINCT pieces, all
    distinct; beyond, DISTINCT colours given greedily in removal order, each piece the first colour after
    its own turn in the cycle that no piece it touches has yet (the least used among them when all are),
    so that touching pieces differ and the colours are used evenly."""
    k = int(labels.max())
    if k <= DISTINCT:
        return _golden_colors(k)
    palette = _golden_colors(DISTINCT)
    neighbours = touching_pieces(labels)
    chosen = np.full(k, -1)
    for i in range(k):
        taken = np.bincount([chosen[j] for j in neighbours[i] if chosen[j] >= 0], minlength=DISTINCT)
        turn = (i + np.arange(DISTINCT)) % DISTINCT
        chosen[i] = turn[int(np.argmin(taken[turn]))]
    return palette[chosen]


def _hex(rgb: np.ndarray) -> str:
    return "#" + "".join(f"{int(round(c * 255)):02x}" for c in rgb)


def boundary_quads(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The exposed unit faces of the filled voxels of a boolean grid: corners (F, 4, 3), wound
    counter-clockwise seen from outside, and each face's direction index into DIRECTIONS (F,)."""
    padded = np.pad(mask, 1)
    quads, dirs = [], []
    for k, d in enumerate(DIRECTIONS):
        axis, sign = int(np.flatnonzero(d)[0]), int(sum(d))
        neighbour = np.roll(padded, -sign, axis=axis)
        origins = np.argwhere(padded & ~neighbour) - 1
        u, v = (axis + 1) % 3, (axis + 2) % 3
        corners = np.zeros((4, 3), dtype=int)
        corners[:, axis] = 1 if sign > 0 else 0
        corners[:, u] = (0, 1, 1, 0)
        corners[:, v] = (0, 0, 1, 1)
        if sign < 0:
            corners = corners[::-1]
        quads.append(origins[:, None, :] + corners[None, :, :])
        dirs.append(np.full(len(origins), k))
    return np.concatenate(quads), np.concatenate(dirs)


@dataclass(frozen=True)
class Piece:
    quads: np.ndarray  # (F, 4, 3) corners in the assembled position
    dirs: np.ndarray  # (F,) face directions
    center: np.ndarray  # (3,) centroid of its voxel centres


def pieces_of(labels: np.ndarray) -> list[Piece]:
    """Pieces 1..K of a label grid, in order, after checking the ids are 1..K."""
    k = validate_labels(labels)
    out = []
    for i in range(1, k + 1):
        mask = labels == i
        quads, dirs = boundary_quads(mask)
        out.append(Piece(quads, dirs, np.argwhere(mask).mean(axis=0) + 0.5))
    return out


@dataclass(frozen=True)
class Step:
    caption: str
    offsets: np.ndarray  # (K, 3) float: each piece's displacement from its assembled place
    present: np.ndarray  # (K,) bool: the pieces still in the scene


def disassembly_steps(verdict: Verdict, frames_per_move: int | None = None) -> list[Step]:
    """The disassembly as a sequence of scenes: assembled; then, piece by piece, the position after each
    move (or `frames_per_move` evenly spaced positions along it), a removed piece leaving the scene when
    the next one starts; last, piece K alone."""
    k = verdict.pieces
    offsets = np.zeros((k, 3))
    present = np.ones(k, dtype=bool)
    steps = [Step(f"assembled: {k} pieces", offsets.copy(), present.copy())]
    for entry in verdict.disassembly:
        piece = entry["piece"]
        name = f"piece {piece}" + (" (key)" if piece == 1 else "")
        for move in entry["moves"]:
            vec = np.asarray(DIRECTIONS[DIRECTION_NAMES.index(move["direction"])], dtype=float)
            start = offsets[piece - 1].copy()
            frames = 1 if frames_per_move is None else min(move["steps"], frames_per_move)
            for f in range(1, frames + 1):
                offsets[piece - 1] = start + vec * move["steps"] * f / frames
                steps.append(
                    Step(f"{name}: {move['direction']} {move['steps']}", offsets.copy(), present.copy())
                )
        present[piece - 1] = False
    steps.append(Step(f"piece {k} stays", offsets.copy(), present.copy()))
    return steps


def _scene_bounds(pieces: list[Piece], steps: list[Step]) -> tuple[np.ndarray, np.ndarray]:
    """Corner-to-corner bounds of every piece wherever it is shown, so the view never moves."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for step in steps:
        for piece, off, shown in zip(pieces, step.offsets, step.present):
            if shown:
                corners = piece.quads.reshape(-1, 3) + off
                lo, hi = np.minimum(lo, corners.min(axis=0)), np.maximum(hi, corners.max(axis=0))
    return lo, hi


def _collection(
    pieces: list[Piece], offsets: np.ndarray, shown: np.ndarray, colors: np.ndarray
) -> Poly3DCollection:
    verts, faces, edges = [], [], []
    for i, (piece, off) in enumerate(zip(pieces, offsets)):
        if not shown[i]:
            continue
        verts.append(piece.quads + off)
        faces.append(colors[i] * np.asarray(_SHADE)[piece.dirs, None])
        # Black edges mark the key. (Line widths cannot do it: mplot3d depth-sorts the face and edge
        # colours of a collection but not its line widths.)
        edges += [(0, 0, 0) if i == 0 else (0.35, 0.35, 0.35)] * len(piece.quads)
    return Poly3DCollection(
        np.concatenate(verts), facecolors=np.concatenate(faces), edgecolors=edges, linewidths=0.6
    )


def _axes(fig: Figure, position: tuple[int, int, int], lo: np.ndarray, hi: np.ndarray, title: str) -> Axes3D:
    ax = fig.add_subplot(*position, projection="3d")
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    # Zoomed in because mplot3d leaves room for axis labels that are switched off here.
    ax.set_box_aspect(hi - lo, zoom=1.1)
    ax.view_init(elev=_ELEV, azim=_AZIM)
    ax.set_axis_off()
    ax.set_title(title, fontsize=10)
    return ax


def order_caption(k: int) -> str:
    order = (
        " → ".join(["1 (key)", *[str(i) for i in range(2, k)]]) if k <= 8 else f"1 (key) → 2 → … → {k - 1}"
    )
    return f"K = {k} pieces; removal order {order}; piece {k} stays"


def draw_png(labels: np.ndarray, path: str | Path, removal: str | None = None) -> None:
    """The assembled shape and an exploded view, each piece labelled with its number in the removal order."""
    pieces = pieces_of(labels)
    k = len(pieces)
    colors = piece_colors(labels)
    spread = exploded_offsets(pieces, labels.shape)
    shown = np.ones(k, dtype=bool)
    fig = Figure(figsize=(10, 5), dpi=90)
    FigureCanvasAgg(fig)
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.88, wspace=0)
    lo, hi = np.zeros(3), np.asarray(labels.shape, dtype=float)
    ax = _axes(fig, (1, 2, 1), lo, hi, "assembled")
    ax.add_collection3d(_collection(pieces, np.zeros((k, 3)), shown, colors))
    # Labels are drawn over the pieces, so the key is marked even where it is hidden inside; they sit on
    # a face of their piece that the camera sees, not at its centre, which may lie behind another piece.
    view = view_direction(_ELEV, _AZIM)
    solid = labels > 0
    _label(ax, label_point(labels == 1, solid, view, [(solid, np.zeros(3))]), "key", key=True)
    ex_lo, ex_hi = _scene_bounds(pieces, [Step("", spread, shown)])
    numbered = k <= MAX_NUMBERED
    title = "exploded (numbers = removal order)" if numbered else "exploded"
    ax = _axes(fig, (1, 2, 2), ex_lo, ex_hi, title)
    ax.add_collection3d(_collection(pieces, spread, shown, colors))
    for i, at in enumerate(exploded_label_points(labels, spread, view, k if numbered else 1)):
        _label(ax, at, "1 key" if i == 0 else str(i + 1), key=i == 0)
    mode = f", {removal} removal" if removal else ""
    fig.suptitle(order_caption(k) + mode, fontsize=11, y=0.98)
    fig.savefig(path)


def view_direction(elev: float, azim: float) -> np.ndarray:
    """The unit vector from the scene towards mplot3d's camera at `elev`, `azim` (degrees)."""
    e, a = np.radians(elev), np.radians(azim)
    return np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])


def label_point(
    mask: np.ndarray, closed: np.ndarray, view: np.ndarray, scene: list[tuple[np.ndarray, np.ndarray]]
) -> np.ndarray:
    """Where the label of the piece `mask` goes, in the piece's own voxel coordinates: the centre of its
    face nearest the camera (along `view`) among the faces that look towards it and have no voxel of
    `closed` on their other side, the first of the _LABEL_CANDIDATES nearest whose ray towards the
    camera passes through nothing in `scene` (grids drawn at their offsets, in the coordinates of the
    piece's drawing); the nearest when every one is hidden; the piece's centre when it has no such face."""
    padded = np.pad(closed, 1)
    voxels = np.argwhere(mask)
    faces = []
    for d in DIRECTIONS:
        normal = np.asarray(d, dtype=float)
        if normal @ view > 0:
            open_side = ~padded[tuple((voxels + 1 + np.asarray(d)).T)]  # +1: padded coordinates
            faces.append(voxels[open_side] + 0.5 + 0.5 * normal)
    centres = np.concatenate(faces) if faces else np.empty((0, 3))
    if not len(centres):
        return voxels.mean(axis=0) + 0.5
    near = centres[np.argsort(-(centres @ view), kind="stable")[:_LABEL_CANDIDATES]]
    seen = _unhidden(near, view, scene)
    return near[int(np.argmax(seen))] if seen.any() else near[0]


def exploded_offsets(pieces: list[Piece], shape: tuple[int, ...]) -> np.ndarray:
    """Each piece's offset in the exploded view (K, 3): out from the centre by its own distance from it,
    far enough to show every piece."""
    return np.stack([1.5 * (p.center - np.asarray(shape) / 2) for p in pieces])


def exploded_label_points(labels: np.ndarray, spread: np.ndarray, view: np.ndarray, count: int) -> np.ndarray:
    """Where the labels of pieces 1..count go in the exploded view, each piece drawn at its offset in
    `spread`: on a face of its own that the camera sees past the other pieces, tested where they are drawn
    (their offsets are not whole voxels: rounded, a piece in front could be missed)."""
    voxels = np.argwhere(labels > 0)
    ids = labels[tuple(voxels.T)]
    order = np.argsort(ids, kind="stable")
    starts = np.searchsorted(ids[order], np.arange(1, len(spread) + 1))
    lows = np.minimum.reduceat(voxels[order], starts)
    highs = np.maximum.reduceat(voxels[order], starts) + 1
    boxes = [
        (labels[tuple(slice(a, b) for a, b in zip(low, high))] == i + 1, low + spread[i])
        for i, (low, high) in enumerate(zip(lows, highs))
    ]
    points = []
    for box, at in boxes[:count]:
        # Every piece, itself included, in the coordinates of this piece's box.
        scene = [(other, other_at - at) for other, other_at in boxes]
        points.append(label_point(box, box, view, scene) + at)
    return np.asarray(points).reshape(count, 3)


def _unhidden(points: np.ndarray, view: np.ndarray, scene: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """Whether each point sees the camera: its ray along `view` enters no voxel of the grids of `scene`,
    each drawn at its offset. Exact: the ray is cut where it crosses each grid's voxel planes, and the cell
    at the middle of every piece of positive length is looked up (a ray marched in steps slips past the
    corners of the pieces it grazes)."""
    hit = np.zeros(len(points), dtype=bool)
    axes = np.flatnonzero(view)
    for grid, off in scene:
        # Only the rays that pass through the grid's box are cut (most miss the box of another piece).
        local = points - off
        near = -local[:, axes] / view[axes]
        far = (np.asarray(grid.shape)[axes] - local[:, axes]) / view[axes]
        enter = np.maximum(np.minimum(near, far).max(axis=1), 0.0)
        through = np.flatnonzero((np.maximum(near, far).min(axis=1) > enter) & ~hit)
        if not len(through):
            continue
        local = local[through]
        crossings = [np.zeros((len(through), 1))]
        for axis in axes:
            planes = np.arange(grid.shape[axis] + 1)
            crossings.append((planes[None, :] - local[:, axis, None]) / view[axis])
        t = np.sort(np.clip(np.concatenate(crossings, axis=1), 0.0, None), axis=1)
        middle = (t[:, 1:] + t[:, :-1]) / 2
        cells = np.floor(local[:, None, :] + middle[..., None] * view).astype(int)
        inside = np.all((cells >= 0) & (cells < np.asarray(grid.shape)), axis=2) & (np.diff(t, axis=1) > 1e-9)
        blocked = np.zeros(inside.shape, dtype=bool)
        blocked[inside] = grid[tuple(cells[inside].T)]
        hit[through] = blocked.any(axis=1)
    return np.logical_not(hit)


def _label(ax: Axes3D, at: np.ndarray, text: str, key: bool) -> None:
    ax.text(
        *at,
        text,
        fontsize=8,
        ha="center",
        va="center",
        fontweight="bold" if key else "normal",
        bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="black" if key else "none", alpha=0.8),
    )


def write_picture(labels: np.ndarray, verdict: Verdict, out_dir: Path) -> None:
    """The picture writer `rllock.files.assembly.write_assembly` takes: assembly.png next to assembly.json."""
    draw_png(labels, Path(out_dir) / "assembly.png", verdict.removal)


def write_gif(labels: np.ndarray, verdict: Verdict, path: str | Path) -> None:
    """The disassembly animated: the key first, each piece along its verified moves."""
    pieces = pieces_of(labels)
    colors = piece_colors(labels)
    steps = disassembly_steps(verdict, _FRAMES_PER_MOVE)
    lo, hi = _scene_bounds(pieces, steps)
    fig = Figure(figsize=(5, 5), dpi=80)
    canvas = FigureCanvasAgg(fig)
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.92)
    ax = _axes(fig, (1, 1, 1), lo, hi, "")
    frames = []
    for step in steps:
        for coll in list(ax.collections):
            coll.remove()
        ax.add_collection3d(_collection(pieces, step.offsets, step.present, colors))
        ax.set_title(step.caption, fontsize=10)
        canvas.draw()
        frames.append(Image.fromarray(np.asarray(canvas.buffer_rgba())[..., :3]).quantize(colors=128))
    # Linger on the first and last scenes so that the loop reads as a story.
    durations = [1200] + [180] * (len(frames) - 2) + [1500]
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=durations, loop=0)


def _mesh_arrays(piece: Piece) -> tuple[np.ndarray, np.ndarray]:
    """Shared vertices (V, 3) and triangles (T, 3) of a piece's exposed faces."""
    vertices, inverse = np.unique(piece.quads.reshape(-1, 3), axis=0, return_inverse=True)
    quads = inverse.reshape(-1, 4)
    triangles = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    return vertices, triangles


def _typed(values: np.ndarray, dtype: str = "i2") -> dict:
    """A plotly.js typed array (int16 by default): a few bytes a number in the page instead of decimals."""
    return {"dtype": dtype, "bdata": base64.b64encode(values.astype("<" + dtype).tobytes()).decode("ascii")}


def _frame_data(meshes: list[tuple[np.ndarray, np.ndarray]], step: Step) -> list[dict]:
    """Every piece's vertices at one step of the disassembly."""
    out = []
    for (vertices, _), off, shown in zip(meshes, step.offsets, step.present):
        # A removed piece collapses to one point: its triangles have no area and draw nothing.
        at = vertices + off if shown else np.broadcast_to(vertices[0], vertices.shape)
        out.append({"type": "mesh3d", "x": _typed(at[:, 0]), "y": _typed(at[:, 1]), "z": _typed(at[:, 2])})
    return out


def _controls(count: int) -> tuple[dict, dict]:
    """(the slider over `count` steps, the play and pause buttons)."""
    still = {"mode": "immediate", "frame": {"duration": 0, "redraw": True}, "transition": {"duration": 0}}
    play = {**still, "fromcurrent": True, "frame": {"duration": 700, "redraw": True}}
    slider = {
        "active": 0,
        "x": 0.12,
        "len": 0.88,
        "y": 0,
        "pad": {"t": 10, "b": 10},
        "currentvalue": {"prefix": "step "},
        "steps": [{"method": "animate", "label": str(s), "args": [[str(s)], still]} for s in range(count)],
    }
    buttons = {
        "type": "buttons",
        "direction": "left",
        "x": 0.12,
        "y": 0,
        "xanchor": "right",
        "yanchor": "top",
        "pad": {"t": 45, "r": 10},
        "buttons": [
            {"label": "▶", "method": "animate", "args": [None, play]},
            {"label": "❚❚", "method": "animate", "args": [[None], still]},
        ],
    }
    return slider, buttons


def _scene(lo: np.ndarray, hi: np.ndarray) -> dict[str, object]:
    """Fixed axes around every step, in the assembly's proportions."""
    span = hi - lo
    scene: dict[str, object] = {
        f"{a}axis": {"range": [float(lo[n]), float(hi[n])], "autorange": False, "title": {"text": a}}
        for n, a in enumerate("xyz")
    }
    scene.update(
        aspectmode="manual",
        aspectratio={a: float(span[n] / span.max()) for n, a in enumerate("xyz")},
        camera={"eye": {"x": 1.0, "y": -1.4, "z": 0.9}},
    )
    return scene


def write_html(labels: np.ndarray, verdict: Verdict, path: str | Path) -> None:
    """One self-contained page (plotly.js embedded, no network): a 3D view to turn and zoom, and a
    slider and play button that step through the disassembly."""
    import plotly.io  # imported here: only the HTML page needs plotly

    pieces = pieces_of(labels)
    k = len(pieces)
    colors = piece_colors(labels)
    steps = disassembly_steps(verdict)
    meshes = [_mesh_arrays(p) for p in pieces]
    names = [f"piece {i + 1}" + (" (key)" if i == 0 else "") for i in range(k)]
    traces = [
        {
            **xyz,
            "i": _typed(tri[:, 0], "i4"),
            "j": _typed(tri[:, 1], "i4"),
            "k": _typed(tri[:, 2], "i4"),
            "color": _hex(colors[i]),
            "flatshading": True,
            "name": names[i],
            "showlegend": True,
            "hovertemplate": names[i] + "<extra></extra>",
        }
        for i, (xyz, (_, tri)) in enumerate(zip(_frame_data(meshes, steps[0]), meshes))
    ]
    summary = f"<br><sup>{order_caption(k)}, {verdict.removal} removal</sup>"
    titles = [f"step {s}/{len(steps) - 1}: {step.caption}{summary}" for s, step in enumerate(steps)]
    # Every frame sets every piece, so that the slider may jump to any step from any other.
    frames = [
        {
            "name": str(s),
            "data": _frame_data(meshes, step),
            "traces": list(range(k)),
            "layout": {"title": {"text": t}},
        }
        for s, (step, t) in enumerate(zip(steps, titles))
    ]
    slider, buttons = _controls(len(steps))
    layout = {
        "title": {"text": titles[0], "x": 0.02, "font": {"size": 16}},
        "scene": _scene(*_scene_bounds(pieces, steps)),
        "sliders": [slider],
        "updatemenus": [buttons],
        "margin": {"l": 0, "r": 0, "t": 70, "b": 0},
    }
    # Built as plain data, not graph objects: plotly's per-array validation takes seconds on big assemblies.
    plotly.io.write_html(
        {"data": traces, "layout": layout, "frames": frames},
        path,
        validate=False,
        include_plotlyjs=True,
        full_html=True,
        auto_play=False,
    )
