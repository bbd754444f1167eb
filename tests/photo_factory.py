"""Seeded product-style photos with exact masks, for segmentation and planning tests.

Objects (cylinder, box, bottle, free-form blob) are drawn at 2× and averaged down, shaded, optionally
printed (stripes, text-like marks, grain), then placed on a white, grey or gradient studio
background with a soft contact shadow, a blurred cast shadow and sensor noise. The true mask is
the object's pixel coverage ≥ 0.5 at the output resolution.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass

import cv2
import numpy as np

SHAPES = ("cylinder", "box", "bottle", "blob")
BACKGROUNDS = ("white", "grey", "gradient")
TEXTURES = ("flat", "stripes", "print", "grain")


@dataclass(frozen=True)
class PhotoSpec:
    shape: str
    background: str
    texture: str
    seed: int
    size: int = 320


def _cylinder(xs, ys, rng):
    cx, rx = rng.uniform(0.42, 0.58), rng.uniform(0.14, 0.22)
    top, bottom = rng.uniform(0.2, 0.32), rng.uniform(0.7, 0.82)
    body = (np.abs(xs - cx) <= rx) & (ys >= top) & (ys <= bottom)
    body |= ((xs - cx) / rx) ** 2 + ((ys - bottom) / 0.04) ** 2 <= 1
    body |= ((xs - cx) / rx) ** 2 + ((ys - top) / 0.04) ** 2 <= 1
    return body, cx, rx, bottom + 0.03


def _box(xs, ys, rng):
    x0, x1 = rng.uniform(0.2, 0.3), rng.uniform(0.55, 0.65)
    y0, y1 = rng.uniform(0.3, 0.38), rng.uniform(0.74, 0.82)
    d = rng.uniform(0.1, 0.16)
    front = (xs >= x0) & (xs <= x1) & (ys >= y0) & (ys <= y1)
    side = (xs > x1) & (xs <= x1 + d) & (ys >= y0 - (xs - x1) * 0.5) & (ys <= y1 - (xs - x1) * 0.5)
    lid = (ys < y0) & (ys >= y0 - d * 0.5) & (xs >= x0 + (y0 - ys) / 0.5) & (xs <= x1 + (y0 - ys) / 0.5)
    return front | side | lid, (x0 + x1 + d) / 2, (x1 + d - x0) / 2, y1 + 0.02


def _bottle(xs, ys, rng):
    cx, rx = rng.uniform(0.45, 0.55), rng.uniform(0.11, 0.15)
    shoulder_y = rng.uniform(0.36, 0.44)
    body = (np.abs(xs - cx) <= rx) & (ys >= shoulder_y) & (ys <= 0.84)
    body |= ((xs - cx) / rx) ** 2 + ((ys - shoulder_y) / 0.08) ** 2 <= 1
    body |= (np.abs(xs - cx) <= 0.045) & (ys >= 0.16) & (ys <= shoulder_y)
    body |= (np.abs(xs - cx) <= 0.055) & (ys >= 0.11) & (ys <= 0.18)
    return body, cx, rx, 0.86


def _blob(xs, ys, rng):
    cx, cy = rng.uniform(0.45, 0.55), rng.uniform(0.45, 0.55)
    ang = np.arctan2(ys - cy, xs - cx)
    radius = np.full_like(xs, rng.uniform(0.22, 0.3))
    for k in range(2, 6):
        radius += rng.uniform(0.0, 0.05 / k * 2) * np.cos(k * ang + rng.uniform(0, 2 * np.pi))
    inside = np.hypot(xs - cx, ys - cy) <= radius
    return inside, cx, 0.25, cy + 0.28


_SHAPE_FN = {"cylinder": _cylinder, "box": _box, "bottle": _bottle, "blob": _blob}


def _texture(kind: str, xs, ys, base: np.ndarray, rng) -> np.ndarray:
    colour = np.broadcast_to(base, (*xs.shape, 3)).copy()
    accent = np.array(colorsys.hsv_to_rgb(rng.uniform(0, 1), rng.uniform(0.5, 0.9), rng.uniform(0.2, 0.9)))
    if kind == "stripes":
        period = rng.uniform(0.015, 0.03)
        colour[(np.floor(ys / period) % 2) == 0] = accent
    elif kind == "print":
        label = (ys > 0.45) & (ys < 0.7)
        colour[label] = (0.95, 0.94, 0.9)
        marks = label & ((np.floor(xs / 0.011) + np.floor(ys / 0.023)) % 3 == 0) & (rng.random(xs.shape) > 0.0)
        colour[marks] = accent
        checker = (ys >= 0.7) & (((np.floor(xs / 0.008) + np.floor(ys / 0.008)) % 2) == 0)
        colour[checker] = 0.15
    elif kind == "grain":
        colour = colour + rng.normal(0.0, 0.12, xs.shape)[..., None]
    elif kind != "flat":
        raise ValueError(f"unknown texture {kind!r}")
    return colour


def _background(kind: str, xs, ys, rng) -> np.ndarray:
    if kind == "white":
        bg = np.full((*xs.shape, 3), rng.uniform(0.94, 0.99))
        return bg * (1.0 - 0.05 * ys[..., None])  # studio fall-off
    if kind == "grey":
        return np.full((*xs.shape, 3), rng.uniform(0.55, 0.75)) * np.array([1.0, 1.0, rng.uniform(0.97, 1.03)])
    if kind == "gradient":
        top = np.array(colorsys.hsv_to_rgb(rng.uniform(0, 1), rng.uniform(0.05, 0.25), 0.97))
        bottom = top * rng.uniform(0.6, 0.75)
        t = (0.7 * ys + 0.3 * xs)[..., None]
        return top * (1 - t) + bottom * t
    raise ValueError(f"unknown background {kind!r}")


def product_photo(spec: PhotoSpec) -> tuple[np.ndarray, np.ndarray]:
    """(H×W×3 uint8 RGB photo, H×W bool true mask) for ``spec``, deterministic in its seed."""
    rng = np.random.default_rng(spec.seed)
    n = 2 * spec.size
    ys, xs = (np.mgrid[0:n, 0:n].astype(np.float64) + 0.5) / n
    inside, cx, rx, floor_y = _SHAPE_FN[spec.shape](xs, ys, rng)
    base = np.array(colorsys.hsv_to_rgb(rng.uniform(0, 1), rng.uniform(0.5, 0.9), rng.uniform(0.35, 0.85)))
    colour = _texture(spec.texture, xs, ys, base, rng)
    u = np.clip((xs - cx) / rx, -1, 1)
    shade = 0.55 + 0.45 * np.clip(-0.4 * u + 0.9 * np.sqrt(1 - u**2), 0, 1)  # cylindrical light from the left
    obj = np.clip(colour * shade[..., None], 0, 1)
    bg = _background(spec.background, xs, ys, rng)
    contact = np.exp(-(((xs - cx - 0.03) / (rx * 1.4)) ** 2 + ((ys - floor_y) / 0.03) ** 2))
    cast = cv2.GaussianBlur(inside.astype(np.float32), (0, 0), n * 0.02)
    cast = np.roll(cast, (int(0.03 * n), int(0.05 * n)), axis=(0, 1))
    bg = bg * (1 - 0.4 * contact[..., None]) * (1 - 0.25 * cast[..., None])
    img = np.where(inside[..., None], obj, bg)
    img = cv2.resize(img, (spec.size, spec.size), interpolation=cv2.INTER_AREA)
    cover = cv2.resize(inside.astype(np.float32), (spec.size, spec.size), interpolation=cv2.INTER_AREA)
    img = img + rng.normal(0.0, 1.5 / 255, img.shape)
    return (np.clip(img, 0, 1) * 255).round().astype(np.uint8), cover >= 0.5


def segmentation_set(seed: int) -> list[PhotoSpec]:
    """Every shape on every background, textures cycling, seeds derived from ``seed``."""
    specs = []
    for i, (shape, bg) in enumerate((s, b) for s in SHAPES for b in BACKGROUNDS):
        specs.append(PhotoSpec(shape, bg, TEXTURES[i % len(TEXTURES)], seed * 1000 + i))
    return specs
