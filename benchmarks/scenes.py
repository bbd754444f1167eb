"""Procedural product scenes with ground truth: a mug, a bottle, a carton, a vase, a sneaker, a lamp, a
chair and a toy figure, then a food tin, a gift box, a woven basket and a torch with fine detail, each
one closed ``TexturedMesh`` with a single texture atlas.

They give the benchmarks an object whose true shape and texture are known, and a "product photo" of
it that goes through the same reference stage as a real photo:

* Every part (body, handle, leg, head, ...) is built from a primitive with its own parametric UVs and
  its own painted tile; the tiles are packed into one atlas with edge-padded margins, so bilinear
  lookups never bleed from a neighbouring tile. Each texture mixes large flat colour regions with
  detail (prints, stripes, text-like marks, barcodes, grain) coarse enough to survive a 128–256 px
  render: the benchmark measures both colour deviation and lost detail.
* The fine scenes (tin, gift, basket, torch) keep their appearance in the high spatial-frequency
  band: small print, a tartan, a basket weave, a diamond knurl, with periods of ``FINE_PERIOD_PX`` px
  in a ``BENCH_SIZE`` render, above 0.6 of its DCT band (the 2-D prior's high-pass bound). Periods
  are chosen in texels from each tile's texels per render pixel (``_fine_period``); a revolved part
  may spread its turn over several tiles (``sectors``) for the texels this needs. Their backs differ
  from their fronts, and each has a thin part: a ring pull, ribbon loops, a cane handle, a lanyard ring.
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

SCENE_NAMES: tuple[str, ...] = ("mug", "bottle", "box", "vase", "sneaker", "lamp", "chair", "figure",
                                "tin", "gift", "basket", "torch")
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

# The fine scenes (tin, gift, basket, torch) size their patterns for the quality benchmark's renders:
# FINE_PERIOD_PX pixels at BENCH_SIZE puts a pattern's frequency at 2 / FINE_PERIOD_PX ≈ 0.7 of the
# render's DCT band, above the 2-D prior's high-pass bound r = 0.6 (periods under 3.33 px).
BENCH_SIZE = 128
FINE_PERIOD_PX = 2.8

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


def _revolve(profile: Sequence[tuple[float, float]], around: int = AROUND, sectors: int = 1,
             weights: Sequence[float] | None = None) -> tuple[np.ndarray, ...]:
    """Surface of revolution about the y axis of a polyline (r, y) running from one pole (r = 0) to
    the other, up the outside, so the surface is closed and outward-wound.

    u = angle / 2π with u = 0.5 facing +z (the seam sits at the back, away from the reference camera);
    v = arc length along the profile, normalised (``_arc_v``: ``weights`` spend more or fewer texels
    on chosen segments). Each pole gets one vertex per segment (its own u), so pole triangles are one
    per segment and never degenerate. Returns (vertices, faces, uvs, canon).

    ``sectors`` > 1 splits the turn into that many equal sectors, sector j centred on u = 0.5 + j /
    sectors (j = 0 faces the camera, j = sectors / 2 the back), each with its own seam copies and its
    own local u ∈ [0, 1]: vertices come sector by sector, so ``_revolved_part`` can give each sector
    its own tile, ``sectors`` times the texels around the turn."""
    prof = np.asarray(profile, dtype=np.float64)
    if prof.ndim != 2 or prof.shape[0] < 3 or prof[0, 0] != 0.0 or prof[-1, 0] != 0.0:
        raise ValueError("a revolution profile needs ≥ 3 points (r, y) starting and ending on the axis")
    if (prof[1:-1, 0] <= 0.0).any() or (np.linalg.norm(np.diff(prof, axis=0), axis=1) == 0.0).any():
        raise ValueError("profile points between the poles must have r > 0 and be distinct")
    if sectors < 1 or (sectors > 1 and around % (2 * sectors)):
        # Sector boundaries sit half a sector off the front: on whole segments only for multiples of 2k.
        raise ValueError(f"{around} segments do not split into {sectors} sectors (need a multiple of {2 * sectors})")
    v_of = _arc_v(prof, weights)
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


def _revolved_part(profile: Sequence[tuple[float, float]], texture: np.ndarray, around: int = AROUND,
                   sectors: int = 1, weights: Sequence[float] | None = None) -> Part:
    """A surface of revolution; with ``sectors`` > 1 the texture is that many tiles side by side
    (``_sector_texture``), sector j of the turn on tile j."""
    if texture.shape[:2] != (TILE, sectors * TILE):
        raise ValueError(f"{sectors} sector(s) need a {TILE}×{sectors * TILE} texture, got {texture.shape[:2]}")
    vertices, faces, uvs, canon = _revolve(profile, around, sectors, weights)
    per = uvs.shape[0] // sectors
    tiled = [_tile_uv(uvs[j * per:(j + 1) * per], (j, 0), (sectors, 1)) for j in range(sectors)]
    return Part(vertices, faces, np.concatenate(tiled), canon, texture)


def _torus_part(major: float, minor: float, texture: np.ndarray, around: int = 48, tube: int = 24) -> Part:
    vertices, faces, uvs, canon = _torus(major, minor, around, tube)
    return Part(vertices, faces, _tile_uv(uvs), canon, texture)


def _box_part(size: tuple[float, float, float], faces_texture: np.ndarray) -> Part:
    vertices, faces, uvs, canon = _box(size)
    return Part(vertices, faces, uvs, canon, faces_texture)


def _arc_v(profile: Sequence[tuple[float, float]], weights: Sequence[float] | None = None) -> np.ndarray:
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


def _luma(colour: Colour) -> float:
    """Rec. 709 luma: the brightness the benchmark's grey spectra see."""
    r, g, b = colour
    return 0.2126 * r + 0.7152 * g + 0.0722 * b


def _with_luma(colour: Colour, luma: float) -> Colour:
    """``colour`` scaled to a given ``_luma`` (clipped to [0, 1]): the fine scenes set their large regions
    apart by hue more than by brightness, so the fine print, not the layout, holds the contrast."""
    r, g, b = colour
    scale = luma / max(_luma(colour), 1e-6)
    return (min(r * scale, 1.0), min(g * scale, 1.0), min(b * scale, 1.0))


class Canvas:
    """A tile's content being painted, addressed in the part's own (u, v) ∈ [0, 1]² (v up; row 0 at
    v = 1). Detail sizes are in texels: a tile spans roughly 100–250 px of a 256 px render, so marks
    of 3+ texels stay visible (not sub-pixel). ``aspect`` is the width / height of the surface the tile
    covers (a box face, half a turn of a can): ``lettering`` keeps letters round on a stretched tile."""

    def __init__(self, colour: Colour, height: int = CONTENT, width: int = CONTENT, aspect: float = 1.0) -> None:
        self.img = np.empty((height, width, 3), dtype=np.float32)
        self.img[:] = colour
        self.h, self.w = height, width
        self.aspect = aspect
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
                paper: Colour = (0.97, 0.95, 0.88), bars: tuple[int, int] = (2, 6),
                gaps: tuple[int, int] = (2, 5)) -> None:
        """A white patch with black bars ``bars`` texels wide (upper bound excluded), ``gaps`` apart:
        by default 2–5 texels, a few pixels in the render; 1–2 where a tile has texels to spare."""
        rows, cols = self._slices(u0, u1, v0, v1)
        self.img[rows, cols] = paper
        x = cols.start + 3
        while x < cols.stop - 6:
            bar = int(rng.integers(*bars))
            self.img[rows.start + 3:rows.stop - 3, x:x + bar] = (0.05, 0.05, 0.06)
            x += bar + int(rng.integers(*gaps))

    def _glyph_grid(self, sideways: bool) -> tuple[float, float, int, int]:
        """Cells per texel across and along a line of text, and the grid's (width, height) in cells:
        physically square cells, as fine as the tile's coarser axis (``aspect``)."""
        ku, kv = (1.0, 1.0 / self.aspect) if self.aspect >= 1.0 else (self.aspect, 1.0)
        gw, gh = max(1, round(self.w * ku)), max(1, round(self.h * kv))
        return ((ku, kv) if sideways else (kv, ku)) + (gw, gh)

    def text_length(self, text: str, height: float, font: int = cv2.FONT_HERSHEY_SIMPLEX, thickness: int = 1,
                    sideways: bool = False) -> float:
        """The length in texels ``lettering`` gives ``text``."""
        k_across, k_along, _, _ = self._glyph_grid(sideways)
        scale = height * k_across / cv2.getTextSize("H", font, 1.0, thickness)[0][1]
        return cv2.getTextSize(text, font, scale, thickness)[0][0] / k_along

    def lettering(self, text: str, u: float, v: float, height: float, colour: Colour, align: str = "left",
                  font: int = cv2.FONT_HERSHEY_SIMPLEX, thickness: int = 1, sideways: bool = False) -> None:
        """Real letters in a Hershey font, capitals ``height`` texels tall, baseline through (u, v) with
        the text's left end, centre or right end there (``align``). Drawn without anti-aliasing, so
        1-texel strokes stay crisp: at 4–6 texels the glyphs are the finest print a tile can carry.
        ``sideways`` runs the text along +v, upright on a revolved part laid along +x
        (``_rotation("z", -90.0)``); ``height`` then counts texels along u. On a stretched tile
        (``aspect`` ≠ 1) the text is drawn on a grid of physically square cells and widened onto the
        tile, so letters keep their shape."""
        k_across, _, gw, gh = self._glyph_grid(sideways)
        scale = height * k_across / cv2.getTextSize("H", font, 1.0, thickness)[0][1]
        shift = {"left": 0.0, "centre": 0.5, "right": 1.0}[align] * cv2.getTextSize(text, font, scale, thickness)[0][0]
        if sideways:  # drawn on the transposed grid: text x along v, text down along u
            mask = np.zeros((gw, gh), np.uint8)
            origin = (round(v * gh - shift), round(u * gw))
        else:
            mask = np.zeros((gh, gw), np.uint8)
            origin = (round(u * gw - shift), round((1.0 - v) * gh))
        cv2.putText(mask, text, origin, font, scale, 255, thickness, cv2.LINE_8)
        if sideways:
            mask = np.ascontiguousarray(np.rot90(mask))
        if mask.shape != (self.h, self.w):
            mask = cv2.resize(mask, (self.w, self.h), interpolation=cv2.INTER_NEAREST)
        self.where(mask > 0, colour)

    def small_print(self, rng: np.random.Generator, u0: float, u1: float, v0: float, v1: float, colour: Colour,
                    height: float = 5.0, line: float = 7.0, sideways: bool = False) -> None:
        """A block of small print (ingredients, instructions): ragged lines ``line`` texels apart of
        random lower-case words in real letters ``height`` texels tall (Hershey plain), finer than
        ``text``'s blocks can go. ``sideways`` as in ``lettering``."""
        across, down = ((v0, v1), (u0, u1)) if sideways else ((u0, u1), (v0, v1))
        size = self.h if sideways else self.w
        step = line / (self.w if sideways else self.h)
        # Down the block: decreasing v for upright text, increasing u for sideways text.
        pos = down[0] + step if sideways else down[1] - step
        while (pos <= down[1]) if sideways else (pos >= down[0]):
            end = across[1] - rng.uniform(0.0, 0.3) * (across[1] - across[0])
            words: list[str] = []
            while True:
                word = "".join(chr(97 + int(c)) for c in rng.integers(0, 26, int(rng.integers(2, 9))))
                width = self.text_length(" ".join([*words, word]), height, cv2.FONT_HERSHEY_PLAIN, sideways=sideways)
                if across[0] + width / size > end:
                    break
                words.append(word)
            if words:
                at = (pos, across[0]) if sideways else (across[0], pos)
                self.lettering(" ".join(words), *at, height, colour, font=cv2.FONT_HERSHEY_PLAIN, sideways=sideways)
            pos += step if sideways else -step

    def tartan(self, period_u: float, period_v: float, dark: Colour, accent: Colour | None = None,
               region: tuple[float, float, float, float] = (0.0, 1.0, 0.0, 1.0), every: int = 3,
               coords: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """A woven check over what is painted: bands of ``dark`` warp (across u) and weft (across v)
        half a period wide, ``period_u`` × ``period_v`` texels (floats: ``_fine_period`` sizes them to a
        few render pixels). One set alone shows half mixed with the ground (the weave lets it through),
        both together in full; every ``every``-th period a thin ``accent`` line each way makes it a
        tartan, ``accent=None`` leaves a gingham. ``coords`` (two arrays shaped like the tile, in the
        periods' units) lay the check on other coordinates than the texel grid: a cloth over a pole
        checked in world x, z instead of converging u lines."""
        x, y = coords if coords is not None else (self.u * self.w, self.v * self.h)
        cu, cv = x / period_u, y / period_v
        warp, weft = (cu % 1.0) < 0.5, (cv % 1.0) < 0.5
        u0, u1, v0, v1 = region
        inside = (self.u >= u0) & (self.u < u1) & (self.v >= v0) & (self.v < v1)
        dark_arr = np.asarray(dark, dtype=np.float32)
        mixed = np.where((warp & weft)[..., None], dark_arr, 0.5 * self.img + 0.5 * dark_arr)
        self.img = np.where((inside & (warp | weft))[..., None], mixed, self.img).astype(np.float32)
        if accent is not None:  # a line a sixth of a period wide, in the middle of every few light bands
            line = (((np.floor(cu) % every == 0) & (np.abs(cu % 1.0 - 0.75) < 1 / 12))
                    | ((np.floor(cv) % every == 0) & (np.abs(cv % 1.0 - 0.75) < 1 / 12)))
            self.where(inside & line, accent)

    def knurl(self, period_u: float, period_v: float, region: tuple[float, float, float, float] = (0.0, 1.0, 0.0, 1.0),
              depth: float = 0.45) -> None:
        """Diamond knurling over what is painted: grooves at ±45° (in render pixels, given periods
        that are equal there) cut the surface into diamonds, each a four-facet pyramid lit from the
        upper left. The facets' brightness and the dark grooves make the diamonds read at ~3 px,
        where a flat colour pattern of that size would blur into one tone."""
        a = self.u * self.w / period_u + self.v * self.h / period_v
        b = self.u * self.w / period_u - self.v * self.h / period_v
        da, db = a % 1.0 - 0.5, b % 1.0 - 0.5
        facet = np.where(np.abs(da) > np.abs(db), np.where(da > 0, 1.0 + 0.5 * depth, 1.0 - 0.3 * depth),
                         np.where(db > 0, 1.0 + 0.15 * depth, 1.0 - 0.7 * depth))
        groove = np.maximum(np.abs(da), np.abs(db)) > 0.4
        shade = np.where(groove, 1.0 - depth, facet).astype(np.float32)
        u0, u1, v0, v1 = region
        inside = (self.u >= u0) & (self.u < u1) & (self.v >= v0) & (self.v < v1)
        self.img = np.where(inside[..., None], self.img * shade[..., None], self.img).astype(np.float32)

    def basket_weave(self, rng: np.random.Generator, period_u: float, period_v: float, stake: Colour,
                     weaver: Colour, region: tuple[float, float, float, float] = (0.0, 1.0, 0.0, 1.0)) -> None:
        """Plain basket weave: weavers running around (``period_v`` texels pitch) pass over and under
        upright stakes (``period_u``), one step out of phase on each row. Each strand is shaded round
        (bright middle, dark edges), a weaver darkens where it dives under a stake and each strand
        gets its own slight tint, so the over/under reads at ~3 render px, not as a flat check."""
        cu, cv = self.u * self.w / period_u, self.v * self.h / period_v
        i, j = np.floor(cv).astype(np.int64), np.floor(cu).astype(np.int64)
        fu, fv = cu % 1.0, cv % 1.0
        over = (i + j) % 2 == 0  # the weaver lies on top of the stake here
        rows_tint = 1.0 + 0.08 * rng.standard_normal(int(i.max() - i.min()) + 1)
        cols_tint = 1.0 + 0.06 * rng.standard_normal(int(j.max() - j.min()) + 1)
        weaver_shade = (0.45 + 0.55 * np.sin(math.pi * fv)) * (0.7 + 0.3 * np.sin(math.pi * fu)) \
            * rows_tint[i - i.min()]
        stake_shade = (0.45 + 0.55 * np.sin(math.pi * fu)) * (0.75 + 0.25 * np.sin(math.pi * fv)) \
            * cols_tint[j - j.min()]
        woven = np.where(over[..., None], np.asarray(weaver, np.float32) * weaver_shade[..., None],
                         np.asarray(stake, np.float32) * stake_shade[..., None])
        u0, u1, v0, v1 = region
        inside = (self.u >= u0) & (self.u < u1) & (self.v >= v0) & (self.v < v1)
        self.img = np.where(inside[..., None], woven, self.img).astype(np.float32)

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


def _sector_texture(canvases: Sequence[Canvas]) -> np.ndarray:
    """One tile per sector of a revolved part, side by side (``_revolved_part(..., sectors=k)``):
    canvas 0 faces the camera, canvas k / 2 the back."""
    return np.concatenate([canvas.tile() for canvas in canvases], axis=1)


def _px_per_unit(long_side: float) -> float:
    """Pixels of a ``BENCH_SIZE`` render per unit, seen face-on, of an object whose longer side is
    ``long_side`` units before normalisation (which puts that side on ``FRAME_FILL`` of the frame)."""
    return FRAME_FILL * BENCH_SIZE / long_side


def _texels_per_px(span: float, long_side: float) -> float:
    """Texels per pixel of a ``BENCH_SIZE`` render where a tile's ``CONTENT`` texels cover ``span`` units
    of surface seen face-on (``_px_per_unit``)."""
    return CONTENT / (span * _px_per_unit(long_side))


def _fine_period(span: float, long_side: float, px: float = FINE_PERIOD_PX) -> float:
    """A period in texels that is about ``px`` pixels of a ``BENCH_SIZE`` render (``_texels_per_px``),
    rounded so a whole number of periods fills the tile: the pattern runs on unbroken across a
    revolved part's seam and from one sector's tile to the next."""
    return CONTENT / max(1, round(CONTENT / (px * _texels_per_px(span, long_side))))


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


_PRODUCTS = ("TOMATO SOUP", "BAKED BEANS", "SWEET CORN", "PEACHES", "CHICKPEAS", "PEAR HALVES", "LENTIL SOUP",
             "APRICOTS")
_BRANDS = ("Harvest", "Oakfield", "Marlow", "Sunvale", "Brookes", "Greystone", "Alder", "Northway")
_NUTRIENTS = ("Energy", "Fat", "- saturates", "Carbohydrate", "- sugars", "Fibre", "Protein", "Salt")
_INK = (0.06, 0.06, 0.07)


def _tin(rng: np.random.Generator) -> list[Part]:
    radius, height = 0.36 * rng.uniform(0.92, 1.08), 1.0 * rng.uniform(0.94, 1.06)
    bead, sink = 0.012, 0.025
    # Double-seamed rims stand proud of the wall; the lid is countersunk below the top rim.
    profile = [(0.0, 0.0), (radius - 0.02, 0.0), (radius + bead, 0.02), (radius + bead, 0.045), (radius, 0.06),
               (radius, height - 0.06), (radius + bead, height - 0.045), (radius + bead, height),
               (radius - 0.02, height), (radius - 0.03, height - sink), (0.0, height - sink)]
    # The base is seldom seen: its texels go to the label (the lid keeps half its share for its rings).
    weights = [0.15, 1, 1, 1, 1, 1, 1, 1, 1, 0.5]
    v = _arc_v(profile, weights)
    lo, hi = v[4], v[5]  # the label covers the straight wall
    span = hi - lo
    wall_span = (height - 0.12) / span  # units of wall the tile's height would cover
    per_v = _texels_per_px(wall_span, height)  # texels per render px up the label
    aspect = math.pi * radius / wall_span  # two sectors: half a turn per tile
    metal = _hsv(rng.uniform(0.1, 0.14), rng.uniform(0.0, 0.35), rng.uniform(0.7, 0.82))  # tinplate or gold lacquer
    brand_c, paper_hue, fruit_c, ink_c = _palette(rng, 4, v=(0.55, 0.8))
    paper = _with_luma(tuple(0.3 * c + 0.62 for c in paper_hue), 0.84)  # type: ignore[arg-type]
    brand_c = _with_luma(brand_c, rng.uniform(0.5, 0.62))
    ink_c = _with_luma(ink_c, 0.22)
    product, brand = str(rng.choice(_PRODUCTS)), str(rng.choice(_BRANDS))
    pu, pv = _fine_period(math.pi * radius, height), _fine_period(wall_span, height)
    band_lo, band_hi = hi - 0.3 * span, hi - 0.06 * span
    small, line = max(4.0, 2.0 * per_v), max(6.0, 3.0 * per_v)  # small print: 2 px capitals, 3 px lines

    def metal_and_label(canvas: Canvas) -> None:
        canvas.rect(0.0, 1.0, lo, hi, paper)  # type: ignore[arg-type]
        # The paper is printed with fine pinstripes, the brand band with a halftone screen.
        canvas.stripes(pu, 0.4, _darker(paper, 0.62), "u", (0.0, 1.0, lo, band_lo))  # type: ignore[arg-type]
        canvas.rect(0.0, 1.0, band_lo, band_hi, brand_c)
        dots = ((canvas.u * canvas.w / pu) % 1.0 - 0.5) ** 2 + ((canvas.v * canvas.h / pv) % 1.0 - 0.5) ** 2
        canvas.where((dots < 0.12) & (canvas.v > band_lo) & (canvas.v < band_hi), _darker(brand_c, 0.45))
        for edge in (band_lo - 3 / CONTENT, band_hi + 2 / CONTENT, lo + 0.04 * span):  # thin rules
            canvas.rect(0.0, 1.0, edge, edge + 1 / CONTENT, ink_c)
        for k in (1, 2, 7, 8):  # rolled seams: fine grooves around
            canvas.stripes(pv, 0.5, _darker(metal, 0.65), "v", (0.0, 1.0, v[k], v[k + 1]))
        canvas.stripes(3, 0.4, _darker(metal, 0.7), "v", (0.0, 1.0, v[9], v[10] - 0.01))  # lid rings

    front = Canvas(metal, aspect=aspect)
    metal_and_label(front)
    white = (0.98, 0.97, 0.92)
    front.lettering(product, 0.5, band_lo + 0.07 * span, 6.5 * per_v, white, "centre", cv2.FONT_HERSHEY_DUPLEX, 2)
    front.lettering(brand, 0.5, band_hi - 0.065 * span, 3.0 * per_v, white, "centre", cv2.FONT_HERSHEY_TRIPLEX)
    # The picture: a few fruit on a plate, shaded round with a highlight and a leaf each.
    pic_v, fr = lo + 0.44 * span, 0.065
    front.ellipse(0.5, pic_v - 0.12 * span, 0.21, 0.05 * span, (0.96, 0.96, 0.94))
    front.ellipse(0.5, pic_v - 0.12 * span, 0.18, 0.035 * span, (0.84, 0.85, 0.86))
    for k, du in enumerate(sorted(rng.uniform(-0.11, 0.11, 3))):
        cu, cv = 0.5 + du, pic_v + (0.03 if k == 1 else -0.02) * span
        dist = ((front.u - cu) / fr) ** 2 + ((front.v - cv) / (fr * aspect)) ** 2
        shade = np.clip(1.15 - 0.5 * dist - 3.0 * (front.u - cu), 0.45, 1.25)[..., None]
        front.img = np.where((dist <= 1.0)[..., None], np.asarray(fruit_c, np.float32) * shade,
                             front.img).astype(np.float32)
        front.ellipse(cu - 0.3 * fr, cv + 0.35 * fr * aspect, 0.15 * fr, 0.25 * fr * aspect, (0.97, 0.95, 0.9))
        front.ellipse(cu + 0.25 * fr, cv + 1.1 * fr * aspect, 0.35 * fr, 0.2 * fr * aspect, (0.2, 0.5, 0.15))
    front.lettering(f"in {rng.choice(('rich', 'light', 'natural'))} juice", 0.5, lo + 0.2 * span, 2.6 * per_v,
                    ink_c, "centre", cv2.FONT_HERSHEY_SIMPLEX)
    front.lettering(f"{int(rng.integers(2, 9)) * 50} g", 0.75, lo + 0.075 * span, 2.6 * per_v, ink_c, "centre")
    front.small_print(rng, 0.2, 0.45, lo + 0.06 * span, lo + 0.15 * span, ink_c, small, line)

    back = Canvas(metal, aspect=aspect)
    metal_and_label(back)
    back.lettering(f"{brand} {product.lower()}", 0.5, band_lo + 0.09 * span, 3.2 * per_v, white, "centre")
    # The nutrition table: a title and ruled rows of names and values, on white.
    row = line / CONTENT
    top = band_lo - 0.05 * span
    bottom = top - 1.6 * row - len(_NUTRIENTS) * row
    back.rect(0.3, 0.7, bottom - 0.3 * row, top, (0.98, 0.98, 0.96))
    back.lettering("Nutrition", 0.32, top - 1.2 * row, 1.2 * small, _INK, font=cv2.FONT_HERSHEY_DUPLEX)
    back.lettering("per 100 g", 0.68, top - 1.2 * row, small, _INK, "right", cv2.FONT_HERSHEY_PLAIN)
    back.rect(0.3, 0.7, top - 1.6 * row, top - 1.6 * row + 2 / CONTENT, _INK)
    for k, nutrient in enumerate(_NUTRIENTS):
        base = top - 1.6 * row - (k + 1) * row
        value = f"{rng.uniform(0.1, 40.0):.1f} g" if k else f"{int(rng.integers(150, 1800))} kJ"
        back.lettering(nutrient, 0.32, base + 0.2 * row, small, _INK, font=cv2.FONT_HERSHEY_PLAIN)
        back.lettering(value, 0.68, base + 0.2 * row, small, _INK, "right", cv2.FONT_HERSHEY_PLAIN)
        back.rect(0.3, 0.7, base, base + 1 / CONTENT, (0.35, 0.35, 0.35))
    back.small_print(rng, 0.04, 0.27, lo + 0.08 * span, top, ink_c, small, line)  # ingredients
    back.small_print(rng, 0.73, 0.96, lo + 0.3 * span, top, ink_c, small, line)  # cooking instructions
    back.barcode(rng, 0.74, 0.94, lo + 0.07 * span, lo + 0.26 * span, bars=(1, 4), gaps=(1, 3))
    back.lettering(" ".join(str(int(d)) for d in rng.integers(0, 10, 7)), 0.84, lo + 0.045 * span, small, _INK,
                   "centre", cv2.FONT_HERSHEY_PLAIN)
    for canvas in (front, back):
        canvas.grain(rng, fine=0.03, coarse=0.03)
    body = _revolved_part(_on_axis(profile), _sector_texture([front, back]), sectors=2, weights=weights)

    ring_tex = Canvas((0.9, 0.9, 0.92))  # bright aluminium against the lid
    ring_tex.stripes(3, 0.5, (0.6, 0.6, 0.64), "v")
    ring_tex.grain(rng)
    major = 0.21 * radius * rng.uniform(0.9, 1.1)
    # The ring pull lies on the lid towards the front, sunk a little into it.
    ring = _place(_torus_part(major, 0.009, ring_tex.tile(), around=32, tube=10), rotate=_rotation("x", 90.0),
                  translate=(0.0, height - sink + 0.005, 0.5 * radius))
    return [body, ring]


def _gift(rng: np.random.Generator) -> list[Part]:
    w, h, d = 1.0 * rng.uniform(0.92, 1.08), 0.58 * rng.uniform(0.9, 1.1), 0.75 * rng.uniform(0.9, 1.1)
    lid_h, lip = 0.16 * rng.uniform(0.9, 1.1), 0.015
    ground, dark_hue, ribbon_c, seal_c, lid_hue = _palette(rng, 5, v=(0.55, 0.85))
    dark = _darker(dark_hue, 0.45)  # the check must differ in brightness, not only in hue
    lid_c = _with_luma(lid_hue, _luma(ground))  # the lid: another hue, as bright
    accent = tuple(0.4 * c + 0.6 for c in seal_c)
    loop = 0.12 * rng.uniform(0.9, 1.1)
    long_side = max(w + 2 * lip, h + lip + 2 * loop)
    lw, ld = w + 2 * lip, d + 2 * lip  # the lid overhangs the body

    def face(span_u: float, span_v: float, colour: Colour = ground) -> Canvas:
        canvas = Canvas(colour, aspect=span_u / span_v)
        canvas.tartan(_fine_period(span_u, long_side), _fine_period(span_v, long_side), dark, accent)  # type: ignore[arg-type]
        return canvas

    def ribbon(canvas: Canvas, along: str, span_across: float, span_along: float) -> None:
        """A satin band 0.1 units wide across the face's middle, ``along`` u or v, with grosgrain ribs
        across it ~3 px apart and darker selvedges."""
        half = 0.05 / span_across
        region = (0.5 - half, 0.5 + half, 0.0, 1.0) if along == "v" else (0.0, 1.0, 0.5 - half, 0.5 + half)
        canvas.rect(*region, ribbon_c)
        canvas.stripes(_fine_period(span_along, long_side), 0.4, _darker(ribbon_c, 0.7), "v" if along == "v" else "u",
                       region)
        edge = 1.5 / CONTENT
        for at in (0.5 - half, 0.5 + half - edge):
            canvas.rect(*((at, at + edge, 0.0, 1.0) if along == "v" else (0.0, 1.0, at, at + edge)),
                        _darker(ribbon_c, 0.5))

    body = {name: face(span, h) for name, span in (("front", w), ("right", d), ("back", w), ("left", d))}
    per = _texels_per_px(h, long_side)  # texels per px up the side faces
    shown = (h + lip - lid_h) / h  # the lid hides the body's faces above this v
    # Front: a round foil seal with sunburst ridges ~3 px apart, the maker's name and a date.
    front = body["front"]
    radius = 0.36 * shown * h  # units
    cu, cv = 0.5, 0.5 * shown
    front.ellipse(cu, cv, 1.08 * radius / w, 1.08 * radius / h, _darker(seal_c, 0.55))
    front.ellipse(cu, cv, radius / w, radius / h, seal_c)
    dx, dy = (front.u - cu) * w, (front.v - cv) * h
    rays = 2 * round(math.pi * radius * _px_per_unit(long_side) / FINE_PERIOD_PX)
    ray = (np.arctan2(dy, dx) * rays / (2 * math.pi)) % 1.0 < 0.5
    ring = (dx ** 2 + dy ** 2 < radius ** 2) & (dx ** 2 + dy ** 2 > (0.72 * radius) ** 2)
    front.where(ring & ray, _darker(seal_c, 0.65))
    name = str(rng.choice(_BRANDS))
    front.lettering(name, cu, cv - 0.02 * shown, 2.4 * per, _INK, "centre", cv2.FONT_HERSHEY_TRIPLEX)
    front.lettering(f"EST. {int(rng.integers(1890, 2010))}", cu, cv - 0.2 * shown, 1.6 * per, _INK, "centre",
                    cv2.FONT_HERSHEY_PLAIN)
    # Back: a printed label: "To" and "From" lines and a message in small print, a barcode and the
    # maker's address.
    back = body["back"]
    small, line = max(4.0, 2.0 * per), max(6.0, 3.0 * per)
    back.rect(0.14, 0.86, 0.1 * shown, 0.92 * shown, (0.7, 0.68, 0.62))
    back.rect(0.15, 0.85, 0.115 * shown, 0.905 * shown, (0.94, 0.92, 0.85))
    for label, at in (("To:", 0.8 * shown), ("From:", 0.67 * shown)):
        back.lettering(label, 0.18, at, 2.4 * per, _INK, font=cv2.FONT_HERSHEY_SIMPLEX)
        back.rect(0.18 + back.text_length(label, 2.4 * per) / CONTENT + 0.02, 0.56, at, at + 1 / CONTENT, _INK)
    back.small_print(rng, 0.18, 0.56, 0.14 * shown, 0.58 * shown, (0.2, 0.2, 0.25), small, line)
    back.barcode(rng, 0.62, 0.82, 0.5 * shown, 0.84 * shown, (0.94, 0.92, 0.85), bars=(1, 4), gaps=(1, 3))
    back.small_print(rng, 0.62, 0.83, 0.14 * shown, 0.45 * shown, (0.2, 0.2, 0.25), small, line)
    body["top"] = Canvas(_darker(ground, 0.9))  # under the lid
    body["bottom"] = Canvas(_darker(ground, 0.9))
    for canvas in body.values():
        canvas.grain(rng, fine=0.03, coarse=0.04)
    base = _place(_box_part((w, h, d), _box_texture(body)), translate=(0.0, h / 2, 0.0))

    lid = {}
    for name, span_u, span_v in (("front", lw, lid_h), ("right", ld, lid_h), ("back", lw, lid_h),
                                 ("left", ld, lid_h), ("top", lw, ld), ("bottom", lw, ld)):
        canvas = face(span_u, span_v, lid_c)
        if name != "bottom":
            ribbon(canvas, "v", span_u, span_v)
        if name == "top":
            ribbon(canvas, "u", span_v, span_u)
        canvas.grain(rng, fine=0.03, coarse=0.04)
        lid[name] = canvas
    top = h + lip
    cover = _place(_box_part((lw, lid_h, ld), _box_texture(lid)), translate=(0.0, top - lid_h / 2, 0.0))

    # The bow: two thin satin loops leaning out from a knot, facing the camera.
    bow_tex = Canvas(ribbon_c)
    bow_tex.stripes(3, 0.4, _darker(ribbon_c, 0.7), "u")
    bow_tex.grain(rng)
    bow = bow_tex.tile()
    lean = rng.uniform(30.0, 45.0)
    parts = [base, cover]
    for side in (-1, 1):
        tilt = math.radians(lean)
        centre = (side * 0.92 * loop * math.sin(tilt), top + 0.92 * loop * math.cos(tilt), 0.0)
        parts.append(_place(_torus_part(loop, 0.011, bow, around=40, tube=10), rotate=_rotation("z", -side * lean),
                            translate=centre))
    knot = _plain_box_texture(rng, _darker(ribbon_c, 0.85), lambda c: c.stripes(8, 0.4, _darker(ribbon_c, 0.6)))
    parts.append(_place(_box_part((0.07, 0.05, 0.06), knot), translate=(0.0, top + 0.015, 0.0)))
    return parts


def _basket(rng: np.random.Generator) -> list[Part]:
    top_r, rim_h = 0.45 * rng.uniform(0.95, 1.05), 0.42 * rng.uniform(0.92, 1.08)
    base_r, bead, dome = 0.72 * top_r, 0.022, 0.04 * rng.uniform(0.8, 1.2)
    inner = top_r - 2 * bead
    cloth = [(inner * math.cos(a), rim_h - 0.03 + dome * math.sin(a) ** 1.5) for a in np.linspace(0.0, math.pi / 2, 9)]
    profile = _on_axis([(0.0, 0.0), (base_r - 0.04, 0.0), *_arc(base_r - 0.04, 0.04, 0.04, -90.0, 0.0, 3)[1:],
                        (top_r, rim_h), *_arc(top_r - bead, rim_h, bead, 0.0, 180.0, 6)[1:],
                        (inner, rim_h - 0.03), *cloth[1:]])
    # The base and the cloth take a smaller share of v: the woven wall gets the texels.
    weights = [0.3] + [1.0] * (len(profile) - 10) + [0.6] * 8
    v = _arc_v(profile, weights)
    wall_lo, wall_hi = v[4], v[5]  # profile points 4 and 5 bound the straight flared wall
    rim_hi = v[12]  # the rim bead runs from v[5] to v[12], the cloth from v[13] to the pole
    major = 0.89 * top_r  # the handle
    long_side = max(2 * top_r, 2 * major + 0.03)
    wall_len = math.hypot(top_r - base_r, rim_h - 0.04)
    span_u = 2 * math.pi * (top_r + base_r) / 2 / 4  # four sectors: a quarter turn per tile
    span_v = wall_len / (wall_hi - wall_lo)
    willow = _hsv(rng.uniform(0.07, 0.12), rng.uniform(0.4, 0.6), rng.uniform(0.62, 0.82))  # natural cane
    stake = _darker(willow, 0.8)
    dyed, cloth_c, tag_c, stain = _palette(rng, 4, s=(0.5, 0.85), v=(0.4, 0.75))
    pale = _with_luma(tuple(0.5 * x + 0.5 for x in dyed), 0.8)  # type: ignore[arg-type]  # the back's band
    dyed = _with_luma(dyed, 0.35)
    stain = _with_luma(stain, 0.6 * _luma(willow))  # the foot is dipped in a darker stain
    pu, pv = _fine_period(span_u, long_side), _fine_period(span_v, long_side)
    check = FINE_PERIOD_PX / _px_per_unit(long_side)  # ~3 px in world units
    foot = wall_lo + 0.4 * (wall_hi - wall_lo)  # the base and the lowest rows are stained
    band = wall_lo + 0.55 * (wall_hi - wall_lo)  # dyed rows above
    canvases = []
    for k in range(4):
        c = Canvas(willow)
        c.basket_weave(rng, pu, pv, stake, willow, (0.0, 1.0, 0.0, v[5]))
        c.basket_weave(rng, pu, pv, _darker(stain, 0.8), stain, (0.0, 1.0, 0.0, foot))
        # The rim: cane wrapped round the bead, diagonal turns ~3 px apart.
        turns = (c.u * c.w + c.v * c.h) / pu
        c.where((c.v >= v[5]) & (c.v < rim_hi) & (turns % 1.0 < 0.4), _darker(willow, 0.55))
        # The cloth: a gingham napkin tucked into the rim, checked in world x, z.
        r = np.interp(c.v, v[13:], [p[0] for p in profile[13:]])
        theta = math.pi + 2.0 * math.pi * (0.375 + (k + c.u) / 4)  # ``_revolve``'s angle of sector k
        c.rect(0.0, 1.0, rim_hi, 1.0, _with_luma(tuple(0.3 * x + 0.7 for x in cloth_c), 0.75))  # type: ignore[arg-type]
        c.tartan(check, check, _with_luma(cloth_c, 0.22), region=(0.0, 1.0, rim_hi, 1.0),
                 coords=(r * np.sin(theta), r * np.cos(theta)))
        # A dark band round the front and sides, a wide pale one across the back (k = 2).
        colour, rows = (pale, 6) if k == 2 else (dyed, 3)
        c.basket_weave(rng, pu, pv, _darker(colour, 0.85), colour, (0.0, 1.0, band, band + rows * pv / CONTENT))
        c.grain(rng, fine=0.04, coarse=0.05)
        canvases.append(c)
    body = _revolved_part(profile, _sector_texture(canvases), sectors=4, weights=weights)

    # A thin cane handle: a whole ring whose lower half is buried in the basket under the cloth.
    handle_tex = Canvas(_darker(willow, 0.9))
    wrap = (handle_tex.u * handle_tex.w / 3.0 + handle_tex.v * 2.0) % 1.0
    handle_tex.where(wrap < 0.4, _darker(willow, 0.55))
    handle_tex.grain(rng)
    handle = _place(_torus_part(major, 0.015, handle_tex.tile(), around=64, tube=10), translate=(0.0, major, 0.0))

    # A leather tag with the maker's name, flat against the back wall.
    tw, th = 0.2, 0.11
    tag = {name: Canvas(tag_c, aspect=tw / th) for name in BOX_FACE_NAMES}
    outside = tag["back"]  # the face looking away from the basket (towards −z)
    outside.rect(0.06, 0.94, 0.1, 0.9, _darker(tag_c, 0.8))
    outside.stripes(8, 0.5, _darker(tag_c, 0.45), "u", (0.08, 0.92, 0.14, 0.18))  # stitching
    outside.stripes(8, 0.5, _darker(tag_c, 0.45), "u", (0.08, 0.92, 0.82, 0.86))
    outside.lettering(str(rng.choice(_BRANDS)).upper(), 0.5, 0.47, 60, (0.95, 0.9, 0.75), "centre",
                      cv2.FONT_HERSHEY_DUPLEX, 3)
    outside.lettering("HANDWOVEN", 0.5, 0.27, 30, (0.95, 0.9, 0.75), "centre", cv2.FONT_HERSHEY_PLAIN, 2)
    for canvas in tag.values():
        canvas.grain(rng, fine=0.04)
    slope = math.degrees(math.atan2(top_r - base_r, rim_h))
    tag_y = 0.55 * rim_h
    wall_r = base_r + (top_r - base_r) * tag_y / rim_h
    tag_part = _place(_box_part((tw, th, 0.008), _box_texture(tag)), rotate=_rotation("x", -slope),
                      translate=(0.0, tag_y, -(wall_r - 0.001)))
    return [body, handle, tag_part]


def _torch(rng: np.random.Generator) -> list[Part]:
    body_r, head_r = 0.15 * rng.uniform(0.94, 1.06), 0.22 * rng.uniform(0.94, 1.06)
    tail_len, body_len, head_len = 0.16, 0.8 * rng.uniform(0.92, 1.08), 0.34 * rng.uniform(0.92, 1.08)
    ring_major = 0.07
    long_side = tail_len + body_len + head_len + ring_major
    anodised, accent = _palette(rng, 2, s=(0.5, 0.9), v=(0.35, 0.65))
    # Bright enough for the knurl's facets to show (it shades multiplicatively); a light accent.
    anodised, accent = _with_luma(anodised, rng.uniform(0.3, 0.45)), _with_luma(accent, 0.65)
    white = (0.95, 0.95, 0.92)

    tail_profile = _on_axis([(0.0, 0.0), *_arc(body_r + 0.005 - 0.02, 0.02, 0.02, -90.0, 0.0, 3),
                             (body_r + 0.005, tail_len), (0.0, tail_len)])
    tv = _arc_v(tail_profile)
    tail_tex = Canvas(_darker(anodised, 0.85))
    # Grip rings round the tail cap, ~3 px apart, and the rubber switch boot at its end.
    grip = _fine_period((tail_len - 0.02) / (tv[-2] - tv[-3]), long_side)
    tail_tex.stripes(grip, 0.45, _darker(anodised, 0.45), "v", (0.0, 1.0, tv[-3] + 0.03, tv[-2] - 0.03))
    tail_tex.rect(0.0, 1.0, 0.0, 0.7 * tv[1], (0.16, 0.16, 0.17))  # ridged like a rubber boot
    tail_tex.stripes(_fine_period(tail_len / (tv[-3] - tv[0]), long_side), 0.45, (0.07, 0.07, 0.08), "v",
                     (0.0, 1.0, 0.0, 0.7 * tv[1]))
    tail_tex.grain(rng, fine=0.04)
    tail = _revolved_part(tail_profile, tail_tex.tile(), around=32)

    y0 = tail_len - 0.01
    body_profile = [(0.0, y0), (body_r, y0), (body_r, y0 + body_len), (0.0, y0 + body_len)]
    weights = [0.2, 1.0, 0.2]  # the ends hide inside the tail cap and the head
    bv = _arc_v(body_profile, weights)
    span_v = body_len / (bv[2] - bv[1])
    knurl_hi = bv[1] + 0.68 * (bv[2] - bv[1])  # knurled from the tail; the smooth rest carries the print
    per_u = _texels_per_px(math.pi * body_r, long_side)
    pu, pv = _fine_period(math.pi * body_r, long_side), _fine_period(span_v, long_side)
    sides = []
    for k in range(2):
        c = Canvas(anodised, aspect=math.pi * body_r / span_v)
        c.knurl(pu, pv, (0.0, 1.0, bv[1] + 0.02, knurl_hi), depth=0.65)
        c.stripes(pv, 0.5, _darker(anodised, 0.86), "v", (0.0, 1.0, knurl_hi, bv[2]))  # lathe-turned rings
        c.rect(0.0, 1.0, knurl_hi, knurl_hi + 2 / CONTENT, accent)  # an accent ring
        if k == 0:  # the front: the maker's name and the rating, along the smooth part
            mid, room = 0.5 * (knurl_hi + bv[2]), 0.8 * (bv[2] - knurl_hi) * CONTENT  # texels along v
            name = str(rng.choice(_BRANDS)).upper()
            cap = 3.2 * per_u  # ~3 px capitals, smaller where the name would not fit the smooth part
            cap *= min(1.0, room / c.text_length(name, cap, cv2.FONT_HERSHEY_DUPLEX, 2, sideways=True))
            c.lettering(name, 0.55, mid, cap, white, "centre", cv2.FONT_HERSHEY_DUPLEX, 2, sideways=True)
            rating = f"{int(rng.integers(4, 30)) * 50} LM  IPX{int(rng.integers(4, 9))}"
            cap = 1.8 * per_u
            cap *= min(1.0, room / c.text_length(rating, cap, cv2.FONT_HERSHEY_PLAIN, sideways=True))
            c.lettering(rating, 0.66, mid, cap, accent, "centre", cv2.FONT_HERSHEY_PLAIN, sideways=True)
            c.rect(0.38, 0.38 + 1.5 / CONTENT, knurl_hi + 0.05, bv[2] - 0.05, accent)  # a thin rule above
        c.grain(rng, fine=0.03, coarse=0.03)
        sides.append(c)
    body = _revolved_part(body_profile, _sector_texture(sides), sectors=2, weights=weights)

    h0 = y0 + body_len - 0.02
    head_profile = _on_axis([(0.0, h0), (body_r + 0.004, h0), (body_r + 0.004, h0 + 0.04),
                             (head_r, h0 + 0.45 * head_len), (head_r, h0 + 0.85 * head_len),
                             (head_r + 0.012, h0 + 0.88 * head_len), (head_r + 0.012, h0 + head_len),
                             (head_r - 0.02, h0 + head_len), (head_r - 0.03, h0 + head_len - 0.015),
                             (0.0, h0 + head_len - 0.015)])
    head_weights = [0.2, 1, 1, 1, 1, 1, 1, 1, 1.5]
    hv = _arc_v(head_profile, head_weights)
    head_arc = float(np.dot(np.linalg.norm(np.diff(np.asarray(head_profile), axis=0), axis=1), head_weights))
    ring_period = _fine_period(head_arc, long_side)  # rings ~3 px apart along the profile
    head_tex = Canvas(anodised)
    # Cooling fins round the flare; the cylinder stays smooth; crenellations round the bezel.
    head_tex.stripes(ring_period, 0.45, _darker(anodised, 0.5), "v", (0.0, 1.0, hv[2], hv[3]))
    head_tex.stripes(ring_period, 0.5, _darker(anodised, 0.86), "v", (0.0, 1.0, hv[3], hv[5]))  # lathe-turned
    head_tex.stripes(_fine_period(2 * math.pi * head_r, long_side), 0.5, _darker(anodised, 0.5), "u",
                     (0.0, 1.0, hv[5], hv[7]))
    # The lens: reflector rings and the LED in the middle.
    head_tex.rect(0.0, 1.0, hv[8], 1.0, (0.85, 0.87, 0.89))
    head_tex.stripes(ring_period, 0.45, (0.5, 0.52, 0.56), "v", (0.0, 1.0, hv[8], 1.0 - 0.12 * (1.0 - hv[8])))
    head_tex.rect(0.0, 1.0, 1.0 - 0.1 * (1.0 - hv[8]), 1.0, (1.0, 0.93, 0.55))
    head_tex.grain(rng, fine=0.03, coarse=0.03)
    head = _revolved_part(head_profile, head_tex.tile(), weights=head_weights)

    # A pocket clip on the back: a thin steel strip, its far end pressed onto the body.
    clip_len = 0.3 * rng.uniform(0.9, 1.1)
    clip = _place(_box_part((0.035, clip_len, 0.012), _plain_box_texture(rng, (0.78, 0.79, 0.8), lambda c: None)),
                  rotate=_rotation("x", 2.0), translate=(0.0, y0 + body_len - 0.06 - clip_len / 2, -(body_r + 0.004)))

    ring_tex = Canvas((0.75, 0.76, 0.78))
    ring_tex.stripes(3, 0.5, (0.45, 0.46, 0.5), "u")
    ring_tex.grain(rng)
    # A thin split ring through the tail cap's lanyard hole, hanging below the axis.
    ring = _place(_torus_part(ring_major, 0.009, ring_tex.tile(), around=32, tube=10),
                  translate=(0.4 * body_r, 0.05 - ring_major, 0.0))
    lying = _rotation("z", -90.0)  # the torch lies along +x, head to the right
    return [_place(part, rotate=lying) for part in (tail, body, head, clip, ring)]


_BUILDERS: dict[str, Callable[[np.random.Generator], list[Part]]] = {
    "mug": _mug, "bottle": _bottle, "box": _carton, "vase": _vase, "sneaker": _sneaker, "lamp": _lamp,
    "chair": _chair, "figure": _figure, "tin": _tin, "gift": _gift, "basket": _basket, "torch": _torch,
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
