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


def _grey_for_lightness(lightness: float) -> float:
    """The sRGB grey level (0–1) whose CIE L* is ``lightness`` (inverse of the sRGB → L* curve)."""
    f = (lightness + 16.0) / 116.0
    y = f**3 if f**3 > 216 / 24389 else (lightness / (24389 / 27))
    return float(12.92 * y if y <= 0.0031308 else 1.055 * y ** (1 / 2.4) - 0.055)


def _lightness_of_grey(g: float) -> float:
    y = g / 12.92 if g <= 0.04045 else ((g + 0.055) / 1.055) ** 2.4
    return float(116.0 * y ** (1 / 3) - 16.0 if y > 216 / 24389 else y * 24389 / 27)


def white_on_white_photo(delta_e: float, seed: int, shape: str = "cylinder",
                         size: int = 320) -> tuple[np.ndarray, np.ndarray]:
    """A near-white product on a white sweep, ``delta_e`` CIE L* below the backdrop behind it.

    What such catalog shots hold: a backdrop ≈ 252/255 with a little fall-off, a grey seam line
    where the floor meets the wall (across the whole frame, partly behind the object), gentle
    shading on the object (±1 ΔE), a soft contact shadow and a blurred cast shadow, sensor noise.
    """
    rng = np.random.default_rng(seed)
    n = 2 * size
    ys, xs = (np.mgrid[0:n, 0:n].astype(np.float64) + 0.5) / n
    inside, cx, rx, floor_y = _SHAPE_FN[shape](xs, ys, rng)
    backdrop = rng.uniform(0.975, 0.99)
    bg = np.full((n, n), backdrop) * (1.0 - 0.012 * ys)  # fall-off of about 1 ΔE top to bottom
    seam_y = rng.uniform(0.55, 0.65)
    bg = bg * (1 - 0.12 * np.exp(-(((ys - seam_y) * n / 1.2) ** 2)))  # a thin grey line, 2–3 px at output size
    object_l = _lightness_of_grey(backdrop * (1.0 - 0.012 * 0.5)) - delta_e
    grey = _grey_for_lightness(object_l)
    u = np.clip((xs - cx) / rx, -1, 1)
    shade = 1.0 + 0.012 * (np.clip(-0.4 * u + 0.9 * np.sqrt(1 - u**2), 0, 1) - 0.5)  # ≈ ±1 ΔE
    obj = np.clip(grey * shade, 0, 1)
    contact = np.exp(-(((xs - cx) / (rx * 1.3)) ** 2 + ((ys - floor_y) / 0.025) ** 2))
    cast = cv2.GaussianBlur(inside.astype(np.float32), (0, 0), n * 0.03)
    cast = np.roll(cast, (int(0.02 * n), int(0.06 * n)), axis=(0, 1))
    bg = bg * (1 - 0.25 * contact) * (1 - 0.05 * cast)  # high-key light: a faint cast shadow
    img = np.repeat(np.where(inside, obj, bg)[..., None], 3, axis=-1) * np.array([1.0, 0.997, 0.99])
    img = cv2.resize(img, (size, size), interpolation=cv2.INTER_AREA)
    cover = cv2.resize(inside.astype(np.float32), (size, size), interpolation=cv2.INTER_AREA)
    img = img + rng.normal(0.0, 1.5 / 255, img.shape)
    return (np.clip(img, 0, 1) * 255).round().astype(np.uint8), cover >= 0.5


def multipart_photo(parts: int, gap_px: int, seed: int, background: str = "white",
                    size: int = 512) -> tuple[np.ndarray, list[np.ndarray]]:
    """``parts`` separate objects in a row, ``gap_px`` output pixels apart (a pair of shoes, a cutlery
    set, earrings). Returns the photo and one true mask per part (each part's own contact shadow and
    a blurred cast shadow of them all; part sizes vary down to 60 % of the largest)."""
    rng = np.random.default_rng(seed)
    n = 2 * size
    ys, xs = (np.mgrid[0:n, 0:n].astype(np.float64) + 0.5) / n
    gap = 2 * gap_px / n
    widths = rng.uniform(0.6, 1.0, parts)
    widths *= min(0.8 - gap * (parts - 1), 0.2 * parts) / widths.sum()
    x = 0.5 - (widths.sum() + gap * (parts - 1)) / 2
    bg = _background(background, xs, ys, rng)
    img, masks, all_parts = bg.copy(), [], np.zeros((n, n), bool)
    for w in widths:
        cx, half = x + w / 2, w / 2
        height = rng.uniform(0.25, 0.45)
        top, bottom = 0.72 - height, 0.72
        kind = rng.integers(3)
        if kind == 0:  # an ellipse
            part = ((xs - cx) / half) ** 2 + ((ys - (top + bottom) / 2) / (height / 2)) ** 2 <= 1
        elif kind == 1:  # a rounded rectangle
            r = 0.3 * half
            qx, qy = np.maximum(np.abs(xs - cx) - (half - r), 0), np.maximum(np.abs(ys - (top + bottom) / 2)
                                                                             - (height / 2 - r), 0)
            part = qx**2 + qy**2 <= r**2
        else:  # a bottle-like profile: narrow top, wide base
            t = np.clip((ys - top) / height, 0, 1)
            part = (np.abs(xs - cx) <= half * (0.35 + 0.65 * np.sqrt(t))) & (ys >= top) & (ys <= bottom)
        base = np.array(colorsys.hsv_to_rgb(rng.uniform(0, 1), rng.uniform(0.4, 0.9), rng.uniform(0.3, 0.8)))
        u = np.clip((xs - cx) / half, -1, 1)
        shade = 0.6 + 0.4 * np.clip(-0.4 * u + 0.9 * np.sqrt(1 - u**2), 0, 1)
        contact = np.exp(-(((xs - cx) / (half * 1.2)) ** 2 + ((ys - bottom) / 0.02) ** 2))
        img = img * (1 - 0.35 * contact[..., None])
        img = np.where(part[..., None], np.clip(base * shade[..., None], 0, 1), img)
        masks.append(part)
        all_parts |= part
        x += w + gap
    cast = np.roll(cv2.GaussianBlur(all_parts.astype(np.float32), (0, 0), n * 0.02), (int(0.02 * n), int(0.04 * n)),
                   axis=(0, 1))
    img = np.where(all_parts[..., None], img, img * (1 - 0.2 * cast[..., None]))
    img = cv2.resize(img, (size, size), interpolation=cv2.INTER_AREA)
    img = img + rng.normal(0.0, 1.5 / 255, img.shape)
    truths = [cv2.resize(m.astype(np.float32), (size, size), interpolation=cv2.INTER_AREA) >= 0.5 for m in masks]
    return (np.clip(img, 0, 1) * 255).round().astype(np.uint8), truths
