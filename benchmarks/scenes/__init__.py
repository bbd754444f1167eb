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
  are chosen in texels from each tile's texels per render pixel (``painting.fine_period``); a revolved
  part may spread its turn over several tiles (``sectors``) for the texels this needs. Their backs
  differ from their fronts, and each has a thin part: a ring pull, ribbon loops, a cane handle, a
  lanyard ring.
* Parts are closed once their UV-seam copies are welded, outward-wound and free of zero-area faces.
  They may interpenetrate (a handle through a mug wall); the union is still a closed surface per part.
* Frame: y up, front towards +z (``morpheus_core.cameras``). Each scene is normalised like a photo
  prepared by ``ops/intake/prepare.py``: the reference view's silhouette (opacity ≥ 0.5 at 256 px) is
  centred with its longer side filling ``FRAME_FILL`` of the image, so the ground truth and the
  reconstruction share one frame.
* Seeded: ``(name, seed)`` fixes colours, print layout and small shape changes, bit for bit.

The package, by concept: ``parts`` (primitives with their own UVs, placing, profiles, packing into one
atlas), ``painting`` (palettes, ``Canvas``, texture layouts, fine-pattern sizing), ``products`` and
``fine_products`` (one builder per product), ``framing`` (the shared frame and the normalisation into
it); this module holds the public API (``Scene``, ``make_scene``, ``make_scenes``, ``photo_fov_deg``).

    python -m benchmarks.scenes --out outputs/scenes   # writes every scene's photo
"""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from PIL import Image
from torch import Tensor

from benchmarks.scenes.fine_products import FINE_BUILDERS
from benchmarks.scenes.framing import (
    FRAME_FILL,
    MAX_EXTENT,
    NORMALISE_SIZE,
    REFERENCE_DISTANCE,
    REFERENCE_FOV_DEG,
    normalise,
)
from benchmarks.scenes.painting import BENCH_SIZE, FINE_PERIOD_PX, Canvas, Colour
from benchmarks.scenes.parts import AROUND, ATLAS_COLUMNS, BOX_FACE_NAMES, CONTENT, MARGIN, TILE, Part, pack
from benchmarks.scenes.products import BUILDERS
from morpheus_core.cameras import Cameras, orbit
from morpheus_core.render.output import RenderOutput
from morpheus_core.render.textured import TexturedMesh, render_textured, sample_surface

__all__ = [
    "AROUND", "ATLAS_COLUMNS", "BENCH_SIZE", "BOX_FACE_NAMES", "CONTENT", "FINE_PERIOD_PX", "FRAME_FILL", "MARGIN",
    "MAX_EXTENT", "NORMALISE_SIZE", "REFERENCE_DISTANCE", "REFERENCE_FOV_DEG", "SCENE_NAMES", "SHADOW_DARKEST",
    "TILE", "Canvas", "Colour", "Part", "Scene", "main", "make_scene", "make_scenes", "photo_fov_deg",
]

SCENE_NAMES: tuple[str, ...] = ("mug", "bottle", "box", "vase", "sneaker", "lamp", "chair", "figure",
                                "tin", "gift", "basket", "torch")

SHADOW_DARKEST = 0.86  # the contact shadow's darkest value (white = 1)

_BUILDERS = {**BUILDERS, **FINE_BUILDERS}
# Each scene draws from its own stream, so seed s of two scenes never share random numbers.
_STREAM = {name: 7919 * (k + 1) for k, name in enumerate(SCENE_NAMES)}


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
    mesh = normalise(pack(_BUILDERS[name](rng)))
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
