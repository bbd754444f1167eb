"""The asset at its real size: metres (glTF's and AR's unit), origin at the bottom centre, +Y up, front +Z.

The method works in a normalised box ([-1, 1]^3, y up, the front facing +z: ``morpheus_core.cameras``), so
only a uniform scale and a shift are needed: AR viewers (Scene Viewer, AR Quick Look) place a model's
origin on the floor, hence the bottom centre. The scale comes from one known dimension, preferring the
height (the one a photo shows least ambiguously); the others, when known too, are compared with the
scaled bounding box, since a product photographed from an angle or a segmentation that lost a part
shows up as disagreeing ratios.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from morpheus_core.geometry.textured_mesh import BakedTexture

# Bounding-box axis of each dimension in the method's frame: x width, y height, z depth.
AXES = {"height": 1, "width": 0, "depth": 2}


@dataclass(frozen=True)
class SizeFit:
    """How an asset was sized: the dimension the scale came from, the scale, the resulting size in
    metres, and each other given dimension's relative disagreement with the scaled mesh."""

    scaled_by: str
    scale: float
    size_m: dict[str, float]
    disagreement: dict[str, float]

    def worst(self) -> float:
        return max(self.disagreement.values(), default=0.0)


def fit_true_size(baked: BakedTexture, known_m: dict[str, float | None]) -> tuple[BakedTexture, SizeFit]:
    """Scale ``baked`` uniformly so that its first known dimension (height, width, depth) is true, and move its
    bottom centre to the origin. ``known_m``: dimension name → metres or None; at least one must be given."""
    unknown = set(known_m) - set(AXES)
    if unknown:
        raise ValueError(f"unknown dimension(s) {sorted(unknown)}; use {sorted(AXES)}")
    given = {k: v for k, v in known_m.items() if v is not None}
    if not given:
        raise ValueError("no dimension given: at least one of height, width, depth is needed to size the asset")
    for k, v in given.items():
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"{k} must be a positive number of metres, got {v}")
    v = np.asarray(baked.vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0 or not np.isfinite(v).all():
        raise ValueError("the mesh must have finite (N, 3) vertices")
    lo, hi = v.min(axis=0), v.max(axis=0)
    extent = hi - lo
    by = next(name for name in AXES if name in given)
    if extent[AXES[by]] <= 0:
        raise ValueError(f"the mesh has no {by} (flat along axis {AXES[by]}); it cannot be sized by it")
    scale = given[by] / float(extent[AXES[by]])
    centre = np.array([(lo[0] + hi[0]) / 2, lo[1], (lo[2] + hi[2]) / 2])
    out = replace(baked, vertices=((v - centre) * scale).astype(np.float32))
    size = {name: float(extent[axis] * scale) for name, axis in AXES.items()}
    disagreement = {name: abs(size[name] - m) / m for name, m in given.items() if name != by}
    return out, SizeFit(by, scale, size, disagreement)
