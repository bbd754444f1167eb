"""Generate the bundled example product photos (seeded, reproducible).

No photo datasets can be downloaded here, so the examples are drawn procedurally: shaded
objects on a near-white studio background with a soft contact shadow and sensor noise, each
with large flat colour regions and fine print (stripes, text-like marks, hatching). Run
``python examples/make_photos.py`` to rewrite ``examples/photos/``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from PIL import Image, ImageFilter

SIZE = 512
SUPER = 2  # draw at 2× and downsample for anti-aliased edges


def _grid(n: int) -> tuple[np.ndarray, np.ndarray]:
    ys, xs = np.mgrid[0:n, 0:n].astype(np.float64) / n
    return xs, ys


def _text_marks(rng: np.random.Generator, xs: np.ndarray, ys: np.ndarray, box, rows: int) -> np.ndarray:
    """Rows of short dark bars that read like printed words at a glance."""
    x0, y0, x1, y1 = box
    marks = np.zeros_like(xs, dtype=bool)
    row_h = (y1 - y0) / rows
    for r in range(rows):
        top = y0 + r * row_h + 0.25 * row_h
        bottom = top + 0.45 * row_h
        x = x0
        while x < x1:
            w = rng.uniform(0.004, 0.03)
            marks |= (xs >= x) & (xs < min(x + w, x1)) & (ys >= top) & (ys < bottom)
            x += w + rng.uniform(0.003, 0.02)
    return marks


def _cylinder_shade(xs: np.ndarray, cx: float, rx: float) -> np.ndarray:
    u = np.clip((xs - cx) / rx, -1.0, 1.0)
    normal_x = u
    normal_z = np.sqrt(1.0 - u**2)
    light = np.array([-0.45, 0.85])
    lambert = np.clip(normal_x * light[0] + normal_z * light[1], 0.0, 1.0)
    spec = np.clip(normal_x * -0.3 + normal_z * 0.95, 0.0, 1.0) ** 40
    return 0.35 + 0.65 * lambert, spec


def _mug(rng: np.random.Generator, xs, ys):
    cx, rx, top, bottom = 0.46, 0.18, 0.30, 0.78
    body = (np.abs(xs - cx) <= rx) & (ys >= top) & (ys <= bottom)
    body |= ((xs - cx) / rx) ** 2 + ((ys - bottom) / 0.035) ** 2 <= 1.0
    rim = ((xs - cx) / rx) ** 2 + ((ys - top) / 0.035) ** 2 <= 1.0
    inner = ((xs - cx) / (rx * 0.92)) ** 2 + ((ys - top) / 0.028) ** 2 <= 1.0
    hx, hy = cx + rx, 0.53
    ring = ((xs - hx) / 0.11) ** 2 + ((ys - hy) / 0.15) ** 2
    handle = (ring <= 1.0) & (ring >= 0.45) & (xs > cx + rx * 0.9)
    colour = np.zeros((*xs.shape, 3))
    colour[:] = (0.08, 0.22, 0.55)
    band = (ys > 0.45) & (ys < 0.63)
    stripes = band & ((np.floor((ys - 0.45) / 0.018) % 2) == 0)
    colour[band] = (0.93, 0.92, 0.88)
    colour[stripes] = (0.80, 0.12, 0.12)
    marks = _text_marks(rng, xs, ys, (cx - 0.12, 0.66, cx + 0.12, 0.74), 2)
    colour[marks & body] = (0.95, 0.85, 0.25)
    shade, spec = _cylinder_shade(xs, cx, rx)
    img = colour * shade[..., None] + spec[..., None] * 0.5
    img[handle] = np.array((0.08, 0.22, 0.55)) * 0.75
    img[rim] = (0.12, 0.28, 0.62)
    img[inner] = (0.05, 0.08, 0.16)
    mask = body | rim | handle
    return img, mask, (cx, bottom + 0.02, 0.26)


def _bottle(rng: np.random.Generator, xs, ys):
    cx, rx = 0.5, 0.13
    body = (np.abs(xs - cx) <= rx) & (ys >= 0.40) & (ys <= 0.86)
    shoulder = ((xs - cx) / rx) ** 2 + ((ys - 0.40) / 0.09) ** 2 <= 1.0
    neck = (np.abs(xs - cx) <= 0.045) & (ys >= 0.18) & (ys <= 0.36)
    cap = (np.abs(xs - cx) <= 0.052) & (ys >= 0.12) & (ys <= 0.19)
    base = ((xs - cx) / rx) ** 2 + ((ys - 0.86) / 0.025) ** 2 <= 1.0
    mask = body | shoulder | neck | cap | base
    colour = np.zeros((*xs.shape, 3))
    colour[:] = (0.10, 0.45, 0.25)
    label = (ys > 0.50) & (ys < 0.76) & mask
    colour[label] = (0.97, 0.95, 0.90)
    checker = label & (ys > 0.70) & (((np.floor(xs / 0.012) + np.floor(ys / 0.012)) % 2) == 0)
    colour[checker] = (0.15, 0.15, 0.15)
    logo = ((xs - cx) ** 2 + (ys - 0.565) ** 2 <= 0.035**2) & label
    colour[logo] = (0.85, 0.40, 0.05)
    marks = _text_marks(rng, xs, ys, (cx - 0.10, 0.605, cx + 0.10, 0.69), 3)
    colour[marks & label] = (0.10, 0.10, 0.30)
    colour[cap] = (0.75, 0.70, 0.60)
    grain = rng.normal(0.0, 0.035, xs.shape)
    colour[cap] += grain[cap][:, None] * 0.5
    shade, spec = _cylinder_shade(xs, cx, rx)
    img = colour * shade[..., None] + spec[..., None] * 0.6
    return img, mask, (cx, 0.88, 0.2)


def _box(rng: np.random.Generator, xs, ys):
    # Front face, right side and top of a box seen slightly from above-right.
    front = (xs >= 0.22) & (xs <= 0.62) & (ys >= 0.36) & (ys <= 0.82)
    side = (xs > 0.62) & (xs <= 0.78) & (ys >= 0.36 - (xs - 0.62) * 0.55) & (ys <= 0.82 - (xs - 0.62) * 0.55)
    top = (ys < 0.36) & (ys >= 0.36 - 0.088) & (xs >= 0.22 + (0.36 - ys) / 0.55) & (xs <= 0.62 + (0.36 - ys) / 0.55)
    mask = front | side | top
    colour = np.zeros((*xs.shape, 3))
    colour[:] = (0.90, 0.55, 0.10)
    hatch = front & (ys > 0.70) & ((np.floor((xs + ys) / 0.01) % 2) == 0)
    colour[hatch] = (0.55, 0.25, 0.05)
    logo = ((xs - 0.42) ** 2 / 0.09**2 + (ys - 0.48) ** 2 / 0.07**2 <= 1.0) & front
    colour[logo] = (0.20, 0.15, 0.55)
    ring = ((xs - 0.42) ** 2 / 0.06**2 + (ys - 0.48) ** 2 / 0.045**2 <= 1.0) & front
    colour[ring] = (0.95, 0.95, 0.95)
    marks = _text_marks(rng, xs, ys, (0.27, 0.575, 0.57, 0.68), 3)
    colour[marks & front] = (0.12, 0.08, 0.05)
    side_marks = _text_marks(rng, xs, ys, (0.64, 0.45, 0.76, 0.62), 4)
    colour[side_marks & side] = (0.30, 0.18, 0.05)
    shade = np.ones(xs.shape)
    shade[side] = 0.62
    shade[top] = 1.12
    img = colour * shade[..., None]
    return img, mask, (0.5, 0.80, 0.34)


PRODUCTS = {"mug": _mug, "bottle": _bottle, "box": _box}


def render_photo(name: str, seed: int = 0) -> Image.Image:
    """One example photo as an RGB PIL image of SIZE×SIZE."""
    rng = np.random.default_rng(seed + sum(map(ord, name)))
    n = SIZE * SUPER
    xs, ys = _grid(n)
    img, mask, (scx, scy, srx) = PRODUCTS[name](rng, xs, ys)
    background = np.ones((n, n, 3)) * np.array([0.975, 0.972, 0.965])
    background *= 1.0 - 0.04 * ys[..., None]  # a gentle studio falloff
    shadow = np.exp(-(((xs - scx - 0.03) / srx) ** 2 + ((ys - scy) / 0.035) ** 2))
    background *= 1.0 - 0.35 * shadow[..., None]
    out = np.where(mask[..., None], np.clip(img, 0.0, 1.0), background)
    pil = Image.fromarray((out * 255).round().astype(np.uint8)).filter(ImageFilter.GaussianBlur(0.6))
    pil = pil.resize((SIZE, SIZE), Image.Resampling.LANCZOS)
    noisy = np.asarray(pil).astype(np.float64) + rng.normal(0.0, 1.5, (SIZE, SIZE, 3))
    return Image.fromarray(np.clip(noisy, 0, 255).round().astype(np.uint8))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "photos")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    for name in PRODUCTS:
        path = args.out / f"{name}.jpg"
        render_photo(name).save(path, quality=92)
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
