"""Parts of the procedural scenes: closed primitives (surfaces of revolution, tori, boxes), each with
its own parametric UVs and its own painted texture (``Part``), the transforms that place them
(``place``, ``rotation``), the profiles they are revolved from, and ``pack``, which joins a scene's
parts into one ``TexturedMesh`` with a single texture atlas of edge-padded tiles."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from morpheus_core.render.textured import TexturedMesh

TILE = 256  # texels per atlas tile side
MARGIN = 4  # edge-padded texels around each tile's content: bilinear lookups stay inside the tile
CONTENT = TILE - 2 * MARGIN
ATLAS_COLUMNS = 4

AROUND = 64  # segments around a surface of revolution: smooth silhouettes at 256 px


# -- parts: geometry with its own UVs and texture ---------------------------------------------


@dataclass(frozen=True)
class Part:
    """One closed primitive: ``uvs`` address its own ``texture`` (v up, row 0 at v = 1). ``canon`` maps
    every vertex to the first copy of its position: seam copies are snapped to it after each transform,
    so welding by exact position never depends on rounding."""

    vertices: np.ndarray  # (V, 3) float64
    faces: np.ndarray  # (F, 3) int64
    uvs: np.ndarray  # (V, 2) float64 in [0, 1]
    canon: np.ndarray  # (V,) int64
    texture: np.ndarray  # (H, W, 3) float32, padded


def _tile_uv(uv: np.ndarray, cell: tuple[int, int] = (0, 0), cells: tuple[int, int] = (1, 1)) -> np.ndarray:
    """Map local (u, v) ∈ [0, 1]² onto the content of ``cell`` (column, row from the top) of a texture
    ``cells`` (columns, rows) tiles large, skipping each tile's padded margin."""
    col, row = cell
    cols, rows = cells
    u = (col * TILE + MARGIN + uv[:, 0] * CONTENT) / (cols * TILE)
    v = 1.0 - (row * TILE + MARGIN + (1.0 - uv[:, 1]) * CONTENT) / (rows * TILE)
    return np.stack([u, v], axis=-1)


def _revolve(profile: Sequence[tuple[float, float]], around: int = AROUND, sectors: int = 1,
             weights: Sequence[float] | None = None) -> tuple[np.ndarray, ...]:
    """Surface of revolution about the y axis of a polyline (r, y) running from one pole (r = 0) to
    the other, up the outside, so the surface is closed and outward-wound.

    u = angle / 2π with u = 0.5 facing +z (the seam sits at the back, away from the reference camera);
    v = arc length along the profile, normalised (``arc_v``: ``weights`` spend more or fewer texels
    on chosen segments). Each pole gets one vertex per segment (its own u), so pole triangles are one
    per segment and never degenerate. Returns (vertices, faces, uvs, canon).

    ``sectors`` > 1 splits the turn into that many equal sectors, sector j centred on u = 0.5 + j /
    sectors (j = 0 faces the camera, j = sectors / 2 the back), each with its own seam copies and its
    own local u ∈ [0, 1]: vertices come sector by sector, so ``revolved_part`` can give each sector
    its own tile, ``sectors`` times the texels around the turn."""
    prof = np.asarray(profile, dtype=np.float64)
    if prof.ndim != 2 or prof.shape[0] < 3 or prof[0, 0] != 0.0 or prof[-1, 0] != 0.0:
        raise ValueError("a revolution profile needs ≥ 3 points (r, y) starting and ending on the axis")
    if (prof[1:-1, 0] <= 0.0).any() or (np.linalg.norm(np.diff(prof, axis=0), axis=1) == 0.0).any():
        raise ValueError("profile points between the poles must have r > 0 and be distinct")
    if sectors < 1 or (sectors > 1 and around % (2 * sectors)):
        # Sector boundaries sit half a sector off the front: on whole segments only for multiples of 2k.
        raise ValueError(f"{around} segments do not split into {sectors} sectors (need a multiple of {2 * sectors})")
    v_of = arc_v(prof, weights)
    n = prof.shape[0]
    per = around // sectors  # segments per sector
    cols = per + 1  # the last column of a sector repeats the first of the next
    t = np.arange(cols)
    start = 0.5 - 0.5 / sectors  # sector 0 spans u ∈ [start, start + 1 / sectors]
    vertices, uvs, faces, canon = [], [], [], []
    first: dict[int, int] = {}  # angular column (mod around) → the first copy's column, per row
    for j in range(sectors):
        u = start + (j * per + t) / around
        theta = math.pi + 2.0 * math.pi * u
        x = prof[:, :1] * np.sin(theta)[None, :]
        z = prof[:, :1] * np.cos(theta)[None, :]
        y = np.broadcast_to(prof[:, 1:2], x.shape)
        vertices.append(np.stack([x, y, z], axis=-1).reshape(-1, 3) + 0.0)  # + 0.0 turns −0.0 into 0.0
        uu = np.broadcast_to((t / per)[None, :], x.shape).copy()
        # Pole vertices sit mid-segment in u. Segment j's bottom triangle uses the pole copy of column j,
        # its top triangle the copy of column j + 1 (the one unused copy of each pole is clipped into range).
        uu[0, :] = np.minimum((t + 0.5) / per, 1.0)
        uu[-1, :] = np.maximum((t - 0.5) / per, 0.0)
        uvs.append(np.stack([uu, np.broadcast_to(v_of[:, None], x.shape)], axis=-1).reshape(-1, 2))

        index = j * n * cols + np.arange(n * cols).reshape(n, cols)
        column = np.array([first.setdefault(int((j * per + k) % around), j * cols + k) for k in t])
        sector_canon = (column // cols) * n * cols + np.arange(n)[:, None] * cols + column % cols
        sector_canon[0, :] = 0
        sector_canon[-1, :] = (n - 1) * cols
        canon.append(sector_canon.reshape(-1))

        a, b = index[:-1, :-1], index[:-1, 1:]  # (i, j), (i, j + 1)
        c, d = index[1:, :-1], index[1:, 1:]  # (i + 1, j), (i + 1, j + 1)
        # (a, b, d) and (a, d, c): ∂/∂θ × ∂/∂profile points outwards for a profile going up the outside.
        lower = np.stack([a, b, d], axis=-1)
        upper = np.stack([a, d, c], axis=-1)
        faces.append(upper[0])  # bottom pole ring: (a, b) collapse, keep (a, d, c)
        for i in range(1, n - 2):
            faces += [lower[i], upper[i]]
        faces.append(lower[n - 2])  # top pole ring: (c, d) collapse, keep (a, b, d)
    faces_arr = np.concatenate(faces, axis=0).astype(np.int64)
    canon_arr = np.concatenate(canon)
    # sin(π) and sin(3π) differ in the last bits: snap seam and pole copies onto one position.
    return np.concatenate(vertices)[canon_arr], faces_arr, np.concatenate(uvs), canon_arr


def _torus(major: float, minor: float, around: int = 48, tube: int = 24) -> tuple[np.ndarray, ...]:
    """Torus in the xy plane (axis z) centred at the origin: u runs around the ring, v around the tube,
    both seams duplicated. Returns (vertices, faces, uvs, canon)."""
    cols, rows = around + 1, tube + 1
    uu, vv = np.meshgrid(np.arange(cols) / around, np.arange(rows) / tube)  # (rows, cols)
    theta, phi = 2.0 * math.pi * uu, 2.0 * math.pi * vv
    ring = major + minor * np.cos(phi)
    vertices = np.stack([ring * np.cos(theta), ring * np.sin(theta), minor * np.sin(phi)], -1).reshape(-1, 3)
    uvs = np.stack([uu, vv], -1).reshape(-1, 2)
    index = np.arange(rows * cols).reshape(rows, cols)
    canon = index.copy()
    canon[:, -1] = canon[:, 0]
    canon[-1, :] = canon[0, :]
    a, b = index[:-1, :-1], index[:-1, 1:]
    c, d = index[1:, :-1], index[1:, 1:]
    # ∂/∂θ × ∂/∂φ is the outward tube normal, so walk u first: (a, d, c) and (a, b, d).
    faces = np.concatenate([np.stack([a, d, c], -1).reshape(-1, 3), np.stack([a, b, d], -1).reshape(-1, 3)])
    canon = canon.reshape(-1)
    return (vertices + 0.0)[canon], faces.astype(np.int64), uvs, canon


# Box faces as (outward normal, right, up) with right × up = normal; the 3×2 UV layout follows the order:
# top row front, right, back; bottom row left, top, bottom.
_BOX_FACES = (
    ((0, 0, 1), (1, 0, 0), (0, 1, 0)),
    ((1, 0, 0), (0, 0, -1), (0, 1, 0)),
    ((0, 0, -1), (-1, 0, 0), (0, 1, 0)),
    ((-1, 0, 0), (0, 0, 1), (0, 1, 0)),
    ((0, 1, 0), (1, 0, 0), (0, 0, -1)),
    ((0, -1, 0), (1, 0, 0), (0, 0, 1)),
)
BOX_FACE_NAMES = ("front", "right", "back", "left", "top", "bottom")


def _box(size: tuple[float, float, float]) -> tuple[np.ndarray, ...]:
    """Axis-aligned box centred at the origin, four vertices per face, face k's UVs on cell k of a 3×2
    grid (``BOX_FACE_NAMES`` order). Corners are half-size × a sign vector, so the copies of a corner on
    its three faces are bitwise equal. Returns (vertices, faces, uvs, canon)."""
    half = np.asarray(size, dtype=np.float64) / 2.0
    vertices, uvs, faces = [], [], []
    corner_ids: dict[tuple[int, ...], int] = {}
    canon = []
    for k, (normal, right, up) in enumerate(_BOX_FACES):
        n, r, t = (np.asarray(a, dtype=np.float64) for a in (normal, right, up))
        local = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
        base = len(vertices)
        for lu, lv in local:
            sign = n + (2 * lu - 1) * r + (2 * lv - 1) * t
            key = tuple(int(s) for s in sign)
            corner_ids.setdefault(key, len(vertices))
            canon.append(corner_ids[key])
            vertices.append(sign * half)
        uvs.append(_tile_uv(local, (k % 3, k // 3), (3, 2)))
        faces += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
    return (np.asarray(vertices) + 0.0, np.asarray(faces, dtype=np.int64), np.concatenate(uvs),
            np.asarray(canon, dtype=np.int64))


def rotation(axis: str, degrees: float) -> np.ndarray:
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    if axis == "x":
        return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    if axis == "y":
        return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    if axis == "z":
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    raise ValueError(f"axis must be 'x', 'y' or 'z', got {axis!r}")


def place(part: Part, scale: float | Sequence[float] = 1.0, rotate: np.ndarray | None = None,
           translate: Sequence[float] = (0.0, 0.0, 0.0)) -> Part:
    """Scale (positive factors keep the winding), then rotate, then translate; seam copies are re-snapped
    to their canonical vertex so they stay bitwise equal."""
    scale_arr = np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,))
    if (scale_arr <= 0).any():
        raise ValueError(f"scale factors must be positive (a mirror would flip the winding), got {scale}")
    v = part.vertices * scale_arr
    if rotate is not None:
        v = v @ np.asarray(rotate, dtype=np.float64).T
    v = v + np.asarray(translate, dtype=np.float64)
    return Part(v[part.canon], part.faces, part.uvs, part.canon, part.texture)


def revolved_part(profile: Sequence[tuple[float, float]], texture: np.ndarray, around: int = AROUND,
                   sectors: int = 1, weights: Sequence[float] | None = None) -> Part:
    """A surface of revolution; with ``sectors`` > 1 the texture is that many tiles side by side
    (``sector_texture``), sector j of the turn on tile j."""
    if texture.shape[:2] != (TILE, sectors * TILE):
        raise ValueError(f"{sectors} sector(s) need a {TILE}×{sectors * TILE} texture, got {texture.shape[:2]}")
    vertices, faces, uvs, canon = _revolve(profile, around, sectors, weights)
    per = uvs.shape[0] // sectors
    tiled = [_tile_uv(uvs[j * per:(j + 1) * per], (j, 0), (sectors, 1)) for j in range(sectors)]
    return Part(vertices, faces, np.concatenate(tiled), canon, texture)


def torus_part(major: float, minor: float, texture: np.ndarray, around: int = 48, tube: int = 24) -> Part:
    vertices, faces, uvs, canon = _torus(major, minor, around, tube)
    return Part(vertices, faces, _tile_uv(uvs), canon, texture)


def box_part(size: tuple[float, float, float], faces_texture: np.ndarray) -> Part:
    vertices, faces, uvs, canon = _box(size)
    return Part(vertices, faces, uvs, canon, faces_texture)


def arc_v(profile: Sequence[tuple[float, float]], weights: Sequence[float] | None = None) -> np.ndarray:
    """Each profile point's v (normalised arc length), as ``_revolve`` assigns it: painters use it to
    put colour boundaries exactly on profile corners. ``weights`` (one per segment) scale each
    segment's share of v: a weight below 1 on a lid or a base seldom seen leaves more of the tile's
    texels for the wall that carries the print."""
    prof = np.asarray(profile, dtype=np.float64)
    lengths = np.linalg.norm(np.diff(prof, axis=0), axis=1)
    if weights is not None:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != lengths.shape or (w <= 0.0).any():
            raise ValueError(f"need {lengths.shape[0]} positive segment weights, got {w.shape[0]}")
        lengths = lengths * w
    arc = np.concatenate([[0.0], np.cumsum(lengths)])
    return arc / arc[-1]


def pack(parts: Sequence[Part]) -> TexturedMesh:
    """Concatenate the parts and shelf-pack their textures (multiples of ``TILE``) into one atlas,
    remapping each part's UVs into its rectangle."""
    # Parts painted with the same texture object (a chair's legs) share one rectangle.
    slots: dict[int, tuple[int, int]] = {}
    x, y, shelf, width = 0, 0, 0, ATLAS_COLUMNS * TILE
    for part in parts:
        if id(part.texture) in slots:
            continue
        h, w = part.texture.shape[:2]
        if x + w > width:
            x, y, shelf = 0, y + shelf, 0
        slots[id(part.texture)] = (x, y)
        x, shelf = x + w, max(shelf, h)
    height = y + shelf
    atlas = np.zeros((height, width, 3), dtype=np.float32)
    vertices, faces, uvs, offset = [], [], [], 0
    for part in parts:
        h, w = part.texture.shape[:2]
        px, py = slots[id(part.texture)]
        atlas[py:py + h, px:px + w] = part.texture
        u = (px + part.uvs[:, 0] * w) / width
        v = 1.0 - (py + (1.0 - part.uvs[:, 1]) * h) / height
        uvs.append(np.stack([u, v], -1))
        vertices.append(part.vertices)
        faces.append(part.faces + offset)
        offset += part.vertices.shape[0]
    return TexturedMesh(
        vertices=torch.from_numpy(np.concatenate(vertices).astype(np.float32)),
        faces=torch.from_numpy(np.concatenate(faces).astype(np.int64)),
        uvs=torch.from_numpy(np.concatenate(uvs).astype(np.float32)),
        texture=torch.from_numpy(np.clip(atlas, 0.0, 1.0)),
    )


# -- profiles ------------------------------------------------------------------------------------


def arc(cr: float, cy: float, radius: float, start_deg: float, end_deg: float,
         steps: int) -> list[tuple[float, float]]:
    """Points (r, y) on a circle arc, angles measured from +r towards +y, both ends included."""
    angles = np.radians(np.linspace(start_deg, end_deg, steps + 1))
    return [(cr + radius * math.cos(a), cy + radius * math.sin(a)) for a in angles]


def on_axis(profile: list[tuple[float, float]]) -> list[tuple[float, float]]:
    # Arcs that end on the axis give r ≈ 1e-17 from cos(90°): snap to exactly 0 (and keep others > 0).
    return [(0.0 if abs(r) < 1e-9 else r, y) for r, y in profile]


def capsule_profile(radius: float, length: float, steps: int = 12) -> list[tuple[float, float]]:
    """A capsule along y centred at the origin: hemisphere, cylinder of ``length``, hemisphere."""
    half = length / 2.0
    return on_axis(arc(0.0, -half, radius, -90.0, 0.0, steps) + arc(0.0, half, radius, 0.0, 90.0, steps))


def rounded_slab_profile(radius: float, height: float, bevel: float, steps: int = 6) -> list[tuple[float, float]]:
    """A disk of ``height`` with rounded edges of ``bevel`` radius, bottom at y = 0."""
    return on_axis([(0.0, 0.0), *arc(radius - bevel, bevel, bevel, -90.0, 0.0, steps),
                     *arc(radius - bevel, height - bevel, bevel, 0.0, 90.0, steps), (0.0, height)])


def frustum_profile(r_bottom: float, r_top: float, y0: float, y1: float) -> list[tuple[float, float]]:
    return [(0.0, y0), (r_bottom, y0), (r_top, y1), (0.0, y1)]
