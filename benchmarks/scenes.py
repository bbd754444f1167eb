"""Procedural product scenes with ground truth: a mug, a bottle, a carton, a vase, a sneaker, a lamp, a
chair and a toy figure, each one closed ``TexturedMesh`` with a single texture atlas.

They give the benchmarks an object whose true shape and texture are known, and a "product photo" of
it that goes through the same reference stage as a real photo:

* Every part (body, handle, leg, head, ...) is built from a primitive with its own parametric UVs and
  its own painted tile; the tiles are packed into one atlas with edge-padded margins, so bilinear
  lookups never bleed from a neighbouring tile. Each texture mixes large flat colour regions with
  detail (prints, stripes, text-like marks, barcodes, grain) coarse enough to survive a 128–256 px
  render: the benchmark measures both colour deviation and lost detail.
* Parts are closed once their UV-seam copies are welded, outward-wound and free of zero-area faces.
  They may interpenetrate (a handle through a mug wall); the union is still a closed surface per part.
* Frame: y up, front towards +z (``morpheus_core.cameras``). Each scene is normalised like a photo
  prepared by ``ops/intake/prepare.py``: the reference view's silhouette (opacity ≥ 0.5 at 256 px) is
  centred with its longer side filling ``FRAME_FILL`` of the image, so the ground truth and the
  reconstruction share one frame.
* Seeded: ``(name, seed)`` fixes colours, print layout and small shape changes, bit for bit.

    python -m benchmarks.scenes --out outputs/scenes   # writes every scene's photo
"""

from __future__ import annotations

import argparse
import colorsys
import math
import os
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from PIL import Image
from torch import Tensor

from morpheus_core.cameras import Cameras, orbit, reference_camera
from morpheus_core.render.output import RenderOutput
from morpheus_core.render.textured import TexturedMesh, render_textured, sample_surface

SCENE_NAMES: tuple[str, ...] = ("mug", "bottle", "box", "vase", "sneaker", "lamp", "chair", "figure")
# Share of the image side taken by the object's longer side: 1 − 2·border_ratio of ops/intake/prepare.py.
FRAME_FILL = 0.8
REFERENCE_FOV_DEG = 40.0
REFERENCE_DISTANCE = 2.5
NORMALISE_SIZE = 256  # the resolution the frame is fitted (and tested) at
MAX_EXTENT = 0.95  # every vertex stays inside the reconstruction grid's ±1 with a margin

TILE = 256  # texels per atlas tile side
MARGIN = 4  # edge-padded texels around each tile's content: bilinear lookups stay inside the tile
CONTENT = TILE - 2 * MARGIN
ATLAS_COLUMNS = 4

AROUND = 64  # segments around a surface of revolution: smooth silhouettes at 256 px

SHADOW_DARKEST = 0.86  # the contact shadow's darkest value (white = 1)

Colour = tuple[float, float, float]


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


def _revolve(profile: Sequence[tuple[float, float]], around: int = AROUND) -> tuple[np.ndarray, ...]:
    """Surface of revolution about the y axis of a polyline (r, y) running from one pole (r = 0) to
    the other, up the outside, so the surface is closed and outward-wound.

    u = angle / 2π with u = 0.5 facing +z (the seam sits at the back, away from the reference camera);
    v = arc length along the profile, normalised. Each pole gets one vertex per segment (its own u), so
    pole triangles are one per segment and never degenerate. Returns (vertices, faces, uvs, canon)."""
    prof = np.asarray(profile, dtype=np.float64)
    if prof.ndim != 2 or prof.shape[0] < 3 or prof[0, 0] != 0.0 or prof[-1, 0] != 0.0:
        raise ValueError("a revolution profile needs ≥ 3 points (r, y) starting and ending on the axis")
    if (prof[1:-1, 0] <= 0.0).any() or (np.linalg.norm(np.diff(prof, axis=0), axis=1) == 0.0).any():
        raise ValueError("profile points between the poles must have r > 0 and be distinct")
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(prof, axis=0), axis=1))])
    v_of = arc / arc[-1]
    n = prof.shape[0]
    cols = around + 1  # the last column repeats the first with u = 1
    u = np.arange(cols) / around
    theta = math.pi + 2.0 * math.pi * u
    x = prof[:, :1] * np.sin(theta)[None, :]
    z = prof[:, :1] * np.cos(theta)[None, :]
    y = np.broadcast_to(prof[:, 1:2], x.shape)
    vertices = np.stack([x, y, z], axis=-1).reshape(-1, 3) + 0.0  # + 0.0 turns −0.0 into 0.0
    uu = np.broadcast_to(u[None, :], x.shape).copy()
    # Pole vertices sit mid-segment in u. Segment j's bottom triangle uses the pole copy of column j,
    # its top triangle the copy of column j + 1 (the one unused copy of each pole is clipped into range).
    uu[0, :] = np.minimum((np.arange(cols) + 0.5) / around, 1.0)
    uu[-1, :] = np.maximum((np.arange(cols) - 0.5) / around, 0.0)
    uvs = np.stack([uu, np.broadcast_to(v_of[:, None], x.shape)], axis=-1).reshape(-1, 2)

    index = np.arange(n * cols).reshape(n, cols)
    canon = index.copy()
    canon[:, -1] = canon[:, 0]
    canon[0, :] = index[0, 0]
    canon[-1, :] = index[-1, 0]

    a, b = index[:-1, :-1], index[:-1, 1:]  # (i, j), (i, j + 1)
    c, d = index[1:, :-1], index[1:, 1:]  # (i + 1, j), (i + 1, j + 1)
    # (a, b, d) and (a, d, c): ∂/∂θ × ∂/∂profile points outwards for a profile going up the outside.
    lower = np.stack([a, b, d], axis=-1)
    upper = np.stack([a, d, c], axis=-1)
    faces = [upper[0]]  # bottom pole ring: (a, b) collapse, keep (a, d, c)
    for i in range(1, n - 2):
        faces += [lower[i], upper[i]]
    faces.append(lower[n - 2])  # top pole ring: (c, d) collapse, keep (a, b, d)
    faces_arr = np.concatenate(faces, axis=0).astype(np.int64)
    canon = canon.reshape(-1)
    # sin(π) and sin(3π) differ in the last bits: snap seam and pole copies onto one position.
    return vertices[canon], faces_arr, uvs, canon


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
    # ∂/∂φ × ∂/∂θ is the outward tube normal, so walk v first: (a, c, d) and (a, d, b).
    faces = np.concatenate([np.stack([a, c, d], -1).reshape(-1, 3), np.stack([a, d, b], -1).reshape(-1, 3)])
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


def _rotation(axis: str, degrees: float) -> np.ndarray:
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    if axis == "x":
        return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    if axis == "y":
        return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    if axis == "z":
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    raise ValueError(f"axis must be 'x', 'y' or 'z', got {axis!r}")


def _place(part: Part, scale: float | Sequence[float] = 1.0, rotate: np.ndarray | None = None,
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


def _revolved_part(profile: Sequence[tuple[float, float]], texture: np.ndarray, around: int = AROUND) -> Part:
    vertices, faces, uvs, canon = _revolve(profile, around)
    return Part(vertices, faces, _tile_uv(uvs), canon, texture)


def _torus_part(major: float, minor: float, texture: np.ndarray) -> Part:
    vertices, faces, uvs, canon = _torus(major, minor)
    return Part(vertices, faces, _tile_uv(uvs), canon, texture)


def _box_part(size: tuple[float, float, float], faces_texture: np.ndarray) -> Part:
    vertices, faces, uvs, canon = _box(size)
    return Part(vertices, faces, uvs, canon, faces_texture)


def _arc_v(profile: Sequence[tuple[float, float]]) -> np.ndarray:
    """Each profile point's v (normalised arc length), as ``_revolve`` assigns it: painters use it to
    put colour boundaries exactly on profile corners."""
    prof = np.asarray(profile, dtype=np.float64)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(prof, axis=0), axis=1))])
    return arc / arc[-1]


def _pack(parts: Sequence[Part]) -> TexturedMesh:
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


# -- painting ------------------------------------------------------------------------------------


def _hsv(h: float, s: float, v: float) -> Colour:
    r, g, b = colorsys.hsv_to_rgb(h % 1.0, min(max(s, 0.0), 1.0), min(max(v, 0.0), 1.0))
    return (r, g, b)


def _palette(rng: np.random.Generator, count: int, s: tuple[float, float] = (0.6, 0.95),
             v: tuple[float, float] = (0.45, 0.9)) -> list[Colour]:
    """``count`` saturated colours with hues spread around the wheel from a random start, so a scene's
    regions differ clearly in colour (the benchmark measures colour deviation)."""
    start = rng.uniform()
    return [_hsv(start + k / count + rng.uniform(-0.05, 0.05), rng.uniform(*s), rng.uniform(*v))
            for k in range(count)]


def _darker(colour: Colour, factor: float) -> Colour:
    r, g, b = colour
    return (r * factor, g * factor, b * factor)


class Canvas:
    """A tile's content being painted, addressed in the part's own (u, v) ∈ [0, 1]² (v up; row 0 at
    v = 1). Detail sizes are in texels: a tile spans roughly 100–250 px of a 256 px render, so marks
    of 3+ texels stay visible (not sub-pixel)."""

    def __init__(self, colour: Colour, height: int = CONTENT, width: int = CONTENT) -> None:
        self.img = np.empty((height, width, 3), dtype=np.float32)
        self.img[:] = colour
        self.h, self.w = height, width
        jj, ii = np.meshgrid(np.arange(width), np.arange(height))
        self.u = (jj + 0.5) / width
        self.v = 1.0 - (ii + 0.5) / height

    def _slices(self, u0: float, u1: float, v0: float, v1: float) -> tuple[slice, slice]:
        rows = slice(max(0, round((1.0 - v1) * self.h)), min(self.h, round((1.0 - v0) * self.h)))
        cols = slice(max(0, round(u0 * self.w)), min(self.w, round(u1 * self.w)))
        return rows, cols

    def rect(self, u0: float, u1: float, v0: float, v1: float, colour: Colour) -> None:
        self.img[self._slices(u0, u1, v0, v1)] = colour

    def where(self, mask: np.ndarray, colour: Colour) -> None:
        self.img[mask] = colour

    def ellipse(self, cu: float, cv: float, ru: float, rv: float, colour: Colour) -> None:
        self.where(((self.u - cu) / ru) ** 2 + ((self.v - cv) / rv) ** 2 <= 1.0, colour)

    def stripes(self, period: int, duty: float, colour: Colour, along: str = "u",
                region: tuple[float, float, float, float] = (0.0, 1.0, 0.0, 1.0)) -> None:
        """Stripes ``period`` texels apart across ``along`` ("u": vertical stripes), inside ``region``."""
        coord = self.u * self.w if along == "u" else self.v * self.h
        u0, u1, v0, v1 = region
        inside = (self.u >= u0) & (self.u < u1) & (self.v >= v0) & (self.v < v1)
        self.where(inside & ((coord % period) < duty * period), colour)

    def text(self, rng: np.random.Generator, u0: float, u1: float, v0: float, v1: float, colour: Colour,
             line: int = 12, letter: tuple[int, int] = (3, 6)) -> None:
        """Text-like marks: lines of words, each word a run of letter blocks 1–2 texels apart with a few
        ascenders, so they read as print rather than as flat bars."""
        rows, cols = self._slices(u0, u1, v0, v1)
        y = rows.start
        while y + line <= rows.stop:
            x = cols.start + int(rng.integers(0, 6))
            end = cols.stop - int(rng.integers(0, max(1, (cols.stop - cols.start) // 3)))
            while x < end:
                for _ in range(int(rng.integers(2, 8))):
                    lw = int(rng.integers(*letter))
                    if x + lw > end:
                        break
                    top = y + (1 if rng.uniform() < 0.25 else 3)
                    self.img[top:y + line - 3, x:x + lw] = colour
                    x += lw + int(rng.integers(1, 3))
                x += int(rng.integers(5, 9))
            y += line

    def barcode(self, rng: np.random.Generator, u0: float, u1: float, v0: float, v1: float,
                paper: Colour = (0.97, 0.95, 0.88)) -> None:
        """A white patch with black bars 2–5 texels wide (a few pixels in the render)."""
        rows, cols = self._slices(u0, u1, v0, v1)
        self.img[rows, cols] = paper
        x = cols.start + 3
        while x < cols.stop - 6:
            bar = int(rng.integers(2, 6))
            self.img[rows.start + 3:rows.stop - 3, x:x + bar] = (0.05, 0.05, 0.06)
            x += bar + int(rng.integers(2, 5))

    def grain(self, rng: np.random.Generator, fine: float = 0.06, coarse: float = 0.08, cells: int = 6) -> None:
        """Multiplicative noise: smooth blotches (``cells`` across) plus per-2-texel speckle."""
        blotch = cv2.resize(rng.standard_normal((cells, cells)).astype(np.float32), (self.w, self.h),
                            interpolation=cv2.INTER_CUBIC)
        speck = rng.standard_normal(((self.h + 1) // 2, (self.w + 1) // 2)).astype(np.float32)
        speck = np.repeat(np.repeat(speck, 2, axis=0), 2, axis=1)[:self.h, :self.w]
        self.img *= (1.0 + coarse * blotch + fine * speck)[..., None]

    def tile(self) -> np.ndarray:
        """The content edge-padded by ``MARGIN`` texels: one clean atlas tile."""
        img = np.clip(self.img, 0.0, 1.0)
        return np.pad(img, ((MARGIN, MARGIN), (MARGIN, MARGIN), (0, 0)), mode="edge")


def _box_texture(canvases: dict[str, Canvas]) -> np.ndarray:
    """Six face canvases laid out as ``_box`` expects (3×2 tiles)."""
    out = np.zeros((2 * TILE, 3 * TILE, 3), dtype=np.float32)
    for k, name in enumerate(BOX_FACE_NAMES):
        col, row = k % 3, k // 3
        out[row * TILE:(row + 1) * TILE, col * TILE:(col + 1) * TILE] = canvases[name].tile()
    return out


def _plain_box_texture(rng: np.random.Generator, colour: Colour, detail: Callable[[Canvas], None]) -> np.ndarray:
    canvases = {}
    for name in BOX_FACE_NAMES:
        canvas = Canvas(colour)
        detail(canvas)
        canvas.grain(rng)
        canvases[name] = canvas
    return _box_texture(canvases)


# -- profiles ------------------------------------------------------------------------------------


def _arc(cr: float, cy: float, radius: float, start_deg: float, end_deg: float,
         steps: int) -> list[tuple[float, float]]:
    """Points (r, y) on a circle arc, angles measured from +r towards +y, both ends included."""
    angles = np.radians(np.linspace(start_deg, end_deg, steps + 1))
    return [(cr + radius * math.cos(a), cy + radius * math.sin(a)) for a in angles]


def _on_axis(profile: list[tuple[float, float]]) -> list[tuple[float, float]]:
    # Arcs that end on the axis give r ≈ 1e-17 from cos(90°): snap to exactly 0 (and keep others > 0).
    return [(0.0 if abs(r) < 1e-9 else r, y) for r, y in profile]


def _capsule_profile(radius: float, length: float, steps: int = 12) -> list[tuple[float, float]]:
    """A capsule along y centred at the origin: hemisphere, cylinder of ``length``, hemisphere."""
    half = length / 2.0
    return _on_axis(_arc(0.0, -half, radius, -90.0, 0.0, steps) + _arc(0.0, half, radius, 0.0, 90.0, steps))


def _rounded_slab_profile(radius: float, height: float, bevel: float, steps: int = 6) -> list[tuple[float, float]]:
    """A disk of ``height`` with rounded edges of ``bevel`` radius, bottom at y = 0."""
    return _on_axis([(0.0, 0.0), *_arc(radius - bevel, bevel, bevel, -90.0, 0.0, steps),
                     *_arc(radius - bevel, height - bevel, bevel, 0.0, 90.0, steps), (0.0, height)])


def _frustum_profile(r_bottom: float, r_top: float, y0: float, y1: float) -> list[tuple[float, float]]:
    return [(0.0, y0), (r_bottom, y0), (r_top, y1), (0.0, y1)]


# -- scenes --------------------------------------------------------------------------------------


def _mug(rng: np.random.Generator) -> list[Part]:
    height = 1.0 * rng.uniform(0.95, 1.05)
    r_bottom, r_top = 0.36 * rng.uniform(0.95, 1.05), 0.42 * rng.uniform(0.95, 1.05)
    wall = 0.035
    # Up the outside, over the rim, down the inside to the coffee surface.
    profile = _on_axis([(0.0, 0.0), *_arc(r_bottom - 0.04, 0.04, 0.04, -90.0, 0.0, 5), (r_top, height),
                        (r_top - wall, height), (r_top - wall, height - 0.06), (0.0, height - 0.06)])
    v = _arc_v(profile)
    body, band, logo, ink = _palette(rng, 4)
    coffee = (0.28, 0.14, 0.06)
    canvas = Canvas(body)
    canvas.rect(0.0, 1.0, 0.35 * v[-4], 0.62 * v[-4], band)  # a wide band in the middle of the wall
    canvas.stripes(6, 0.5, _darker(band, 0.55), "u", (0.0, 1.0, 0.35 * v[-4], 0.42 * v[-4]))
    canvas.ellipse(0.5, 0.72 * v[-4], 0.07, 0.12, logo)
    canvas.ellipse(0.5, 0.72 * v[-4], 0.035, 0.06, ink)
    canvas.text(rng, 0.4, 0.6, 0.12 * v[-4], 0.3 * v[-4], ink)
    canvas.stripes(5, 0.4, _darker(body, 0.6), "v", (0.0, 1.0, 0.02, 0.1))
    canvas.rect(0.0, 1.0, v[-3], 1.0, coffee)  # the coffee surface (and the inside rim above it)
    canvas.rect(0.0, 1.0, v[-4], v[-3], _darker(body, 1.1))  # the rim top
    canvas.grain(rng)
    handle = Canvas(body)
    handle.stripes(6, 0.5, band, "u")
    handle.grain(rng)
    cup = _revolved_part(profile, canvas.tile())
    ring = _place(_torus_part(0.26 * height, 0.055 * height, handle.tile()),
                  translate=(r_top * 0.92 + 0.13 * height, 0.5 * height, 0.0))
    return [cup, ring]


def _bottle(rng: np.random.Generator) -> list[Part]:
    radius, body_h = 0.3 * rng.uniform(0.93, 1.07), 1.0 * rng.uniform(0.93, 1.07)
    neck, neck_top, cap_r, cap_h = 0.1, body_h + 0.5, 0.125, 0.16
    shoulder = [(neck + (radius - neck) * (0.5 + 0.5 * math.cos(math.pi * t)), body_h + 0.35 * t)
                for t in np.linspace(0.0, 1.0, 17)]
    profile = _on_axis([(0.0, 0.0), *_arc(radius - 0.05, 0.05, 0.05, -90.0, 0.0, 5), *shoulder[:-1],
                        (neck, body_h + 0.35), (neck, neck_top), (cap_r, neck_top), (cap_r, neck_top + cap_h),
                        (0.0, neck_top + cap_h)])
    v = _arc_v(profile)
    glass, paper_hue, block, cap = _palette(rng, 4)
    paper = tuple(0.55 * c + 0.4 for c in paper_hue)  # a pale tint (kept clearly off white)
    # Profile points 6 and 7 bound the straight wall; the label covers most of it.
    label_lo, label_hi = v[6] + 0.12 * (v[7] - v[6]), v[6] + 0.9 * (v[7] - v[6])
    canvas = Canvas(glass)
    canvas.stripes(4, 0.5, _darker(glass, 0.8), "u", (0.0, 1.0, 0.0, label_lo))  # moulded ribs below the label
    canvas.rect(0.0, 1.0, label_lo, label_hi, paper)  # type: ignore[arg-type]
    span = label_hi - label_lo
    canvas.rect(0.0, 1.0, label_hi - 0.3 * span, label_hi, block)
    canvas.stripes(8, 0.35, _darker(block, 0.5), "u", (0.0, 1.0, label_hi - 0.3 * span, label_hi - 0.22 * span))
    canvas.ellipse(0.5, label_hi - 0.55 * span, 0.07, 0.13 * span, _darker(block, 0.7))
    canvas.text(rng, 0.36, 0.64, label_lo + 0.08 * span, label_hi - 0.72 * span, (0.1, 0.1, 0.12))
    canvas.text(rng, 0.05, 0.3, label_lo + 0.1 * span, label_hi - 0.35 * span, _darker(block, 0.6), line=10)
    canvas.barcode(rng, 0.57, 0.69, label_lo + 0.1 * span, label_lo + 0.45 * span)
    canvas.rect(0.0, 1.0, v[-5], 1.0, cap)
    canvas.stripes(4, 0.5, _darker(cap, 0.6), "u", (0.0, 1.0, v[-4], v[-3]))  # cap knurling
    canvas.grain(rng, fine=0.04)
    return [_revolved_part(profile, canvas.tile())]


def _carton(rng: np.random.Generator) -> list[Part]:
    size = (1.0 * rng.uniform(0.9, 1.1), 1.35 * rng.uniform(0.92, 1.08), 0.55 * rng.uniform(0.9, 1.1))
    main, accent, side, ink, second = _palette(rng, 5)
    kraft = (0.72, 0.55, 0.34)
    front = Canvas(main)
    front.rect(0.0, 1.0, 0.62, 0.86, accent)  # the brand band
    front.stripes(6, 0.5, _darker(accent, 0.6), "v", (0.0, 1.0, 0.62, 0.66))
    front.ellipse(0.3, 0.4, 0.18, 0.14, second)
    front.ellipse(0.3, 0.4, 0.09, 0.07, _darker(second, 0.5))
    front.text(rng, 0.1, 0.9, 0.88, 0.98, ink, line=11)
    front.text(rng, 0.55, 0.92, 0.3, 0.56, ink)
    front.text(rng, 0.12, 0.9, 0.68, 0.82, (0.97, 0.96, 0.9), line=16, letter=(5, 10))
    front.barcode(rng, 0.08, 0.36, 0.04, 0.18)
    front.stripes(5, 0.4, _darker(main, 0.7), "u", (0.5, 0.95, 0.04, 0.18))
    canvases = {"front": front}
    for name in ("right", "left", "back"):
        c = Canvas(side if name != "back" else second)
        c.rect(0.0, 1.0, 0.75, 0.9, accent)
        c.text(rng, 0.08, 0.92, 0.2, 0.7, ink)
        canvases[name] = c
    for name in ("top", "bottom"):
        c = Canvas(kraft)
        c.rect(0.0, 1.0, 0.42, 0.58, _darker(kraft, 0.8))  # packing tape
        c.stripes(3, 0.34, _darker(kraft, 0.9), "u")
        canvases[name] = c
    for c in canvases.values():
        c.grain(rng, fine=0.04, coarse=0.05)
    return [_box_part(size, _box_texture(canvases))]


def _vase(rng: np.random.Generator) -> list[Part]:
    height = 1.6 * rng.uniform(0.95, 1.05)
    belly, waist, lip = rng.uniform(0.42, 0.5), rng.uniform(0.15, 0.2), rng.uniform(0.22, 0.28)
    ts = np.linspace(0.0, 1.0, 61)
    # Belly low down, a narrow waist, flaring lip: a smooth bump sum, bounded away from the axis.
    radii = 0.18 + belly * np.exp(-((ts - 0.3) / 0.2) ** 2) + lip * np.exp(-((ts - 1.0) / 0.12) ** 2)
    radii = np.maximum(radii - (0.2 - waist) * np.exp(-((ts - 0.72) / 0.1) ** 2), 0.1)
    wall = [(float(r), float(t * height)) for r, t in zip(radii, ts, strict=True)]
    mouth = float(radii[-1]) - 0.04
    profile = _on_axis([(0.0, 0.0), *wall, (mouth, height), (mouth, height - 0.1), (0.0, height - 0.1)])
    colours = _palette(rng, 5)
    canvas = Canvas(colours[0])
    edges = np.sort(rng.uniform(0.08, 0.9, 6))
    for k in range(0, 6, 2):
        canvas.rect(0.0, 1.0, edges[k], edges[k + 1], colours[1 + k // 2])
    canvas.stripes(7, 0.45, colours[4], "u", (0.0, 1.0, edges[0] + 0.02, edges[0] + 0.07))
    canvas.stripes(5, 0.4, _darker(colours[0], 0.6), "v", (0.0, 1.0, edges[3] + 0.01, edges[4] - 0.01))
    waves = canvas.v - (edges[1] + 0.03) - 0.02 * np.sin(canvas.u * 2 * math.pi * 16)
    canvas.where((waves > 0) & (waves < 0.015), colours[4])
    canvas.rect(0.0, 1.0, 0.95, 1.0, _darker(colours[0], 0.4))  # the dark inside of the mouth
    canvas.grain(rng, fine=0.08, coarse=0.1)
    return [_revolved_part(profile, canvas.tile())]


def _sneaker(rng: np.random.Generator) -> list[Part]:
    length = rng.uniform(1.0, 1.1)  # half length along x
    upper_c, block_c, sole_c, lace_c = _palette(rng, 4)
    sole_c = tuple(0.5 * c + 0.45 for c in sole_c)  # a light rubber tint, still off white
    sole_tex = Canvas(sole_c)  # type: ignore[arg-type]
    sole_tex.stripes(5, 0.4, _darker(sole_c, 0.65), "u", (0.0, 1.0, 0.3, 0.7))  # type: ignore[arg-type]
    sole_tex.rect(0.0, 1.0, 0.0, 0.28, _darker(block_c, 0.5))  # tread
    sole_tex.grain(rng)
    sole = _place(_revolved_part(_rounded_slab_profile(1.0, 0.16, 0.05), sole_tex.tile()),
                  scale=(length, 1.0, 0.38))
    dome = _on_axis([(0.0, 0.1)] + [(0.92 * math.cos(a), 0.1 + 0.8 * math.sin(a))
                                    for a in np.linspace(0.0, math.pi / 2, 25)])
    upper = Canvas(upper_c)
    # The dome's flat bottom (v < rim) hides inside the sole; paint the wall by its own height 0..1.
    rim = _arc_v(dome)[1]
    wall = (upper.v - rim) / (1.0 - rim)
    # The side facing the camera is u ≈ 0.5; the toe (+x) is u = 0.75, the heel u = 0.25.
    upper.where((wall < 0.5) & (np.abs(upper.u - 0.5) < 0.16), block_c)  # side panel
    upper.where((np.abs(upper.u - 0.25) < 0.06) & (wall < 0.85), _darker(block_c, 0.6))  # heel tab
    upper.where((np.abs(upper.u - 0.75) < 0.1) & (wall < 0.45), _darker(upper_c, 0.55))  # toe cap
    swoosh = wall - 0.25 - 1.2 * (upper.u - 0.35) + 6.0 * (upper.u - 0.5) ** 2
    upper.where((np.abs(swoosh) < 0.06) & (np.abs(upper.u - 0.5) < 0.22), lace_c)
    for k in range(6):  # laces across the instep, towards the toe
        s0 = 0.62 + 0.055 * k
        upper.where((np.abs(upper.u - 0.72) < 0.08) & (wall > s0) & (wall < s0 + 0.025), lace_c)
    upper.stripes(4, 0.5, _darker(upper_c, 0.75), "v", (0.0, 1.0, rim, rim + 0.06 * (1.0 - rim)))  # welt
    upper.grain(rng, fine=0.12, coarse=0.06)  # knit mesh
    top = _place(_revolved_part(dome, upper.tile()), scale=(0.85 * length, 1.0, 0.36),
                 translate=(-0.12 * length, 0.0, 0.0))
    # A shoe rises towards the heel: scale heights above the sole by a factor falling from heel to toe
    # (positive everywhere, so the map keeps the winding and the surface closed).
    x = top.vertices[:, 0] / length
    factor = 1.05 - 0.55 * np.clip((x + 1.0) / 2.0, 0.0, 1.0)
    lifted = top.vertices.copy()
    lifted[:, 1] = 0.1 + (lifted[:, 1] - 0.1) * factor
    return [sole, Part(lifted[top.canon], top.faces, top.uvs, top.canon, top.texture)]


def _lamp(rng: np.random.Generator) -> list[Part]:
    metal, shade_c, weave_c, base_c = _palette(rng, 4)
    base_tex = Canvas(base_c)
    base_tex.stripes(6, 0.5, _darker(base_c, 0.6), "u")
    base_tex.grain(rng)
    base = _revolved_part(_rounded_slab_profile(0.38, 0.1, 0.03), base_tex.tile())
    pole_tex = Canvas(metal)
    pole_tex.stripes(8, 0.3, _darker(metal, 0.6), "v")
    pole_tex.grain(rng)
    pole_top = 1.0 * rng.uniform(0.95, 1.05)
    pole = _revolved_part(_frustum_profile(0.035, 0.035, 0.05, pole_top + 0.05), pole_tex.tile(), around=24)
    shade_tex = Canvas(shade_c)
    weave = (np.sin(shade_tex.u * shade_tex.w * math.pi / 3) * np.sin(shade_tex.v * shade_tex.h * math.pi / 3))
    shade_tex.img += 0.12 * weave[..., None]
    shade_tex.rect(0.0, 1.0, 0.2, 0.28, weave_c)
    shade_tex.rect(0.0, 1.0, 0.72, 0.8, weave_c)
    shade_tex.stripes(6, 0.5, _darker(weave_c, 0.6), "u", (0.0, 1.0, 0.22, 0.26))
    shade_tex.grain(rng, fine=0.05)
    shade_h, r_bottom, r_top = 0.55, 0.5 * rng.uniform(0.9, 1.1), 0.3 * rng.uniform(0.9, 1.1)
    shade = _revolved_part(_frustum_profile(r_bottom, r_top, pole_top - 0.15, pole_top - 0.15 + shade_h),
                           shade_tex.tile())
    return [base, pole, shade]


def _chair(rng: np.random.Generator) -> list[Part]:
    wood, pad_c, pattern_c = _palette(rng, 3, s=(0.55, 0.9), v=(0.4, 0.8))
    wood = _darker(wood, 1.0)

    def grain(canvas: Canvas) -> None:
        lines = np.sin(canvas.u * canvas.w * 2 * math.pi / 7 + 3 * np.sin(canvas.v * 9))
        canvas.where(lines > 0.55, _darker(wood, 0.7))

    wood_tex = _plain_box_texture(rng, wood, grain)
    width, depth, seat_y = 1.0, 0.9 * rng.uniform(0.95, 1.05), 0.85 * rng.uniform(0.95, 1.05)
    parts = [_place(_box_part((width, 0.08, depth), wood_tex), translate=(0.0, seat_y, 0.0))]
    # The back legs and backrest are inset: seen from the front, perspective would otherwise leave a
    # sliver of background between front and back legs that segmentation closes.
    back_w = 0.62 * width
    leg = _box_part((0.1, seat_y + 0.02, 0.1), wood_tex)
    for sx in (-1, 1):
        for sz, x in ((1, width / 2 - 0.06), (-1, back_w / 2 - 0.06)):
            parts.append(_place(leg, translate=(sx * x, (seat_y + 0.02) / 2 - 0.01, sz * (depth / 2 - 0.06))))
    back_h = 0.85 * rng.uniform(0.95, 1.05)
    back = _box_part((back_w, back_h, 0.07), wood_tex)
    parts.append(_place(back, rotate=_rotation("x", -8.0),
                        translate=(0.0, seat_y + back_h / 2 - 0.02, -depth / 2 + 0.02)))

    def fabric(canvas: Canvas) -> None:
        canvas.stripes(6, 0.34, pattern_c, "u")
        canvas.stripes(6, 0.34, _darker(pattern_c, 0.7), "v")
        canvas.rect(0.0, 1.0, 0.05, 0.15, _darker(pad_c, 0.5))

    pad_tex = _plain_box_texture(rng, pad_c, fabric)
    pad = _box_part((width - 0.1, 0.07, depth - 0.12), pad_tex)
    parts.append(_place(pad, translate=(0.0, seat_y + 0.07, 0.03)))
    # A back cushion: the face the reference camera sees.
    cushion = _box_part((back_w - 0.12, 0.45, 0.06), pad_tex)
    parts.append(_place(cushion, rotate=_rotation("x", -8.0),
                        translate=(0.0, seat_y + 0.5 * back_h, -depth / 2 + 0.06)))
    return parts


def _figure(rng: np.random.Generator) -> list[Part]:
    skin = _hsv(rng.uniform(0.04, 0.1), rng.uniform(0.35, 0.6), rng.uniform(0.75, 0.95))
    shirt, print_c, trousers, hair, shoes = _palette(rng, 5, v=(0.45, 0.85))
    head_r = 0.28 * rng.uniform(0.95, 1.05)
    head_tex = Canvas(skin)
    head_tex.rect(0.0, 1.0, 0.72, 1.0, hair)
    head_tex.stripes(4, 0.5, _darker(hair, 0.6), "u", (0.0, 1.0, 0.72, 1.0))
    for du in (-0.045, 0.045):  # eyes on the front (u = 0.5), a little above the equator
        head_tex.ellipse(0.5 + du, 0.56, 0.022, 0.045, (0.98, 0.98, 0.98))
        head_tex.ellipse(0.5 + du, 0.56, 0.012, 0.025, (0.05, 0.05, 0.1))
    mouth = (np.abs(head_tex.u - 0.5) < 0.05) & (np.abs(head_tex.v - 0.4 - 8 * (head_tex.u - 0.5) ** 2) < 0.012)
    head_tex.where(mouth, (0.6, 0.05, 0.1))
    head_tex.ellipse(0.42, 0.45, 0.02, 0.03, _darker(skin, 0.85))
    head_tex.grain(rng, fine=0.03, coarse=0.04)
    sphere = _on_axis(_arc(0.0, 0.0, head_r, -90.0, 90.0, 32))
    head = _place(_revolved_part(sphere, head_tex.tile()), translate=(0.0, 1.3, 0.0))

    body_tex = Canvas(shirt)
    body_tex.ellipse(0.5, 0.55, 0.09, 0.16, print_c)
    body_tex.stripes(5, 0.4, _darker(print_c, 0.5), "v", (0.42, 0.58, 0.45, 0.65))
    body_tex.text(rng, 0.4, 0.6, 0.25, 0.38, _darker(shirt, 0.4), line=10)
    body_tex.stripes(6, 0.5, _darker(shirt, 0.75), "v", (0.0, 1.0, 0.0, 0.15))
    body_tex.grain(rng)
    body = _place(_revolved_part(_capsule_profile(0.26, 0.35), body_tex.tile()), translate=(0.0, 0.82, 0.0))

    limb_tex = Canvas(shirt)
    limb_tex.rect(0.0, 1.0, 0.0, 0.3, skin)  # hands at the low end
    limb_tex.stripes(5, 0.4, _darker(shirt, 0.6), "v", (0.0, 1.0, 0.45, 0.6))
    limb_tex.grain(rng)
    leg_tex = Canvas(trousers)
    # Coloured shoes: near-black, neutral ones pass for the contact shadow in classical segmentation.
    leg_tex.rect(0.0, 1.0, 0.0, 0.2, _darker(shoes, 0.7))
    leg_tex.stripes(6, 0.5, _darker(trousers, 0.7), "u", (0.0, 1.0, 0.2, 1.0))
    leg_tex.grain(rng)
    spread = rng.uniform(18.0, 30.0)
    parts = [head, body]
    for side in (-1, 1):
        arm = _revolved_part(_capsule_profile(0.085, 0.5), limb_tex.tile(), around=32)
        parts.append(_place(arm, rotate=_rotation("z", side * spread),
                            translate=(side * (0.3 + 0.25 * math.sin(math.radians(spread))), 0.82, 0.0)))
        leg = _revolved_part(_capsule_profile(0.1, 0.45), leg_tex.tile(), around=32)
        # Legs well apart: a gap of a few pixels would be closed by the reference stage's segmentation.
        parts.append(_place(leg, translate=(side * 0.145, 0.32, 0.0)))
    return parts


_BUILDERS: dict[str, Callable[[np.random.Generator], list[Part]]] = {
    "mug": _mug, "bottle": _bottle, "box": _carton, "vase": _vase, "sneaker": _sneaker, "lamp": _lamp,
    "chair": _chair, "figure": _figure,
}
# Each scene draws from its own stream, so seed s of two scenes never share random numbers.
_STREAM = {name: 7919 * (k + 1) for k, name in enumerate(SCENE_NAMES)}


# -- normalisation ---------------------------------------------------------------------------------


def _extent_px(opacity: np.ndarray) -> tuple[float, float, float, float]:
    """Sub-pixel (x0, x1, y0, y1) of the silhouette: the first and last covered column/row, moved by
    their partial coverage, so the fit is not quantised to whole pixels."""
    cols, rows = opacity.max(axis=0), opacity.max(axis=1)

    def span(profile: np.ndarray) -> tuple[float, float]:
        on = np.flatnonzero(profile > 0.02)
        lo, hi = int(on[0]), int(on[-1])
        return lo + 1.0 - float(profile[lo]), hi + float(profile[hi])

    x0, x1 = span(cols)
    y0, y1 = span(rows)
    return x0, x1, y0, y1


def _reference_opacity(vertices: np.ndarray, mesh: TexturedMesh, size: int) -> np.ndarray:
    probe = TexturedMesh(torch.from_numpy(vertices.astype(np.float32)), mesh.faces, mesh.uvs, mesh.texture)
    with torch.no_grad():
        out = render_textured(probe, reference_camera(), size, size)
    return out.opacity[0, ..., 0].numpy()


def _normalise(mesh: TexturedMesh, iterations: int = 6) -> TexturedMesh:
    """Uniform scale and x/y shift so the reference silhouette at ``NORMALISE_SIZE`` px is centred with
    its longer side ``FRAME_FILL`` of the image; depth is centred on z = 0. Perspective makes one fit
    inexact (nearer parts look larger), so measure and correct a few times."""
    v = mesh.vertices.numpy().astype(np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    v = v - (lo + hi) / 2.0
    size = NORMALISE_SIZE
    px_per_unit = 0.5 * size / (REFERENCE_DISTANCE * math.tan(math.radians(REFERENCE_FOV_DEG) / 2))
    target = FRAME_FILL * size
    v = v * (target / px_per_unit / float(max(hi[0] - lo[0], hi[1] - lo[1])))
    for _ in range(iterations):
        x0, x1, y0, y1 = _extent_px(_reference_opacity(v, mesh, size))
        dx, dy = (x0 + x1) / 2.0 - size / 2.0, (y0 + y1) / 2.0 - size / 2.0
        long_side = max(x1 - x0, y1 - y0)
        if abs(dx) < 0.05 and abs(dy) < 0.05 and abs(long_side - target) < 0.05:
            break
        v[:, 0] -= dx / px_per_unit  # image rows grow downwards, y upwards
        v[:, 1] += dy / px_per_unit
        v = v * (target / long_side)
    if np.abs(v).max() >= MAX_EXTENT:
        raise AssertionError(f"a normalised scene reaches {np.abs(v).max():.3f}, outside ±{MAX_EXTENT}")
    return TexturedMesh(torch.from_numpy(v.astype(np.float32)), mesh.faces, mesh.uvs, mesh.texture)


# -- public API ------------------------------------------------------------------------------------


def photo_fov_deg(fill: float) -> float:
    """The field of view at which the normalised object's longer side fills ``fill`` of the frame."""
    if fill <= 0.0:
        raise ValueError(f"fill must be positive, got {fill}")
    return 2.0 * math.degrees(math.atan(math.tan(math.radians(REFERENCE_FOV_DEG) / 2) * FRAME_FILL / fill))


def _contact_shadow(opacity: np.ndarray) -> np.ndarray:
    """Background brightness (H, W) with a soft grey ellipse centred on the silhouette's bottom edge,
    ``SHADOW_DARKEST`` at its core: a studio contact shadow that segmentation treats as background."""
    size = opacity.shape[0]
    on = opacity >= 0.5
    shade = np.ones_like(opacity, dtype=np.float32)
    if not on.any():
        return shade
    rows, cols = np.flatnonzero(on.any(axis=1)), np.flatnonzero(on.any(axis=0))
    width = float(cols[-1] + 1 - cols[0])
    cx, bottom = (cols[0] + cols[-1] + 1) / 2.0, float(rows[-1] + 1)
    ry = max(2.0, 0.06 * width)
    blob = np.zeros_like(shade)
    cv2.ellipse(blob, (round(cx * 4), round(bottom * 4)), (round(0.5 * width * 4), round(ry * 4)), 0.0, 0.0, 360.0,
                1.0, thickness=-1, lineType=cv2.LINE_AA, shift=2)
    blob = cv2.GaussianBlur(blob, (0, 0), max(1.0, 0.8 * ry, size / 256.0))
    if blob.max() > 0:
        blob /= blob.max()
    return shade - (1.0 - SHADOW_DARKEST) * blob


@dataclass(frozen=True, eq=False)
class Scene:
    """A normalised procedural product (``mesh`` on the CPU, float32) and its seed."""

    name: str
    seed: int
    mesh: TexturedMesh

    def render(self, cameras: Cameras, size: int, background: float = 1.0) -> RenderOutput:
        """``render_textured`` at ``size`` × ``size`` on the cameras' device."""
        with torch.no_grad():
            return render_textured(self.mesh.to(cameras.device), cameras, size, size, background=background)

    def photo(self, size: int = 512, fill: float = FRAME_FILL, shadow: bool = True) -> np.ndarray:
        """A product photo (size, size, 3) uint8 from the reference camera's position: white background,
        soft contact shadow, the object's longer side filling ``fill`` of the frame (> 1 crops it).
        Rendered at 2× (at most 1024 px) and area-averaged down for anti-aliasing."""
        if size < 1:
            raise ValueError(f"size must be positive, got {size}")
        render_px = min(2 * size, 1024)
        camera = orbit(0.0, 0.0, REFERENCE_DISTANCE, photo_fov_deg(fill))
        out = self.render(camera, render_px)
        rgb = out.rgb[0].numpy().astype(np.float32)
        alpha = out.opacity[0].numpy().astype(np.float32)
        if render_px != size:
            interp = cv2.INTER_AREA if render_px > size else cv2.INTER_LINEAR
            rgb = cv2.resize(rgb, (size, size), interpolation=interp)
            alpha = cv2.resize(alpha, (size, size), interpolation=interp)[..., None]
        if shadow:
            # The render is composited on white: swap white for the shadowed background behind the object.
            rgb = rgb + (1.0 - alpha) * (_contact_shadow(alpha[..., 0])[..., None] - 1.0)
        return (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)

    def write_photo(self, path: Path, size: int = 512, fill: float = FRAME_FILL) -> Path:
        """Write ``photo`` as a PNG atomically (a temporary sibling, then ``os.replace``)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp.{os.getpid()}")
        try:
            Image.fromarray(self.photo(size, fill)).save(tmp, format="PNG")
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)
        return path

    def surface_points(self, count: int, generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
        """``count`` points uniform over the surface and their texture colours (``sample_surface``)."""
        return sample_surface(self.mesh, count, generator)


def make_scene(name: str, seed: int = 0) -> Scene:
    """Build, texture and normalise one scene; the same (name, seed) gives bitwise identical results."""
    if name not in _BUILDERS:
        raise ValueError(f"unknown scene {name!r}; choose one of {', '.join(SCENE_NAMES)}")
    if seed < 0:
        raise ValueError(f"seed must be non-negative, got {seed}")
    rng = np.random.default_rng([seed, _STREAM[name]])
    mesh = _normalise(_pack(_BUILDERS[name](rng)))
    return Scene(name=name, seed=seed, mesh=mesh)


def make_scenes(seed: int = 0, names: Iterable[str] = SCENE_NAMES) -> list[Scene]:
    return [make_scene(name, seed) for name in names]


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="folder for <name>.png photos")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--fill", type=float, default=FRAME_FILL)
    args = parser.parse_args(argv)
    for scene in make_scenes(args.seed):
        print(scene.write_photo(args.out / f"{scene.name}.png", args.size, args.fill))


if __name__ == "__main__":
    main()
