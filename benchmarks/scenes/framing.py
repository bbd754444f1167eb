"""The frame every scene shares with a prepared photo: the reference camera (``REFERENCE_FOV_DEG``,
``REFERENCE_DISTANCE``), the share of the image the object fills (``FRAME_FILL``), and ``normalise``,
which scales and centres a packed mesh so its reference silhouette sits in that frame."""

from __future__ import annotations

import math

import numpy as np
import torch

from morpheus_core.cameras import reference_camera
from morpheus_core.render.textured import TexturedMesh, render_textured

# Share of the image side taken by the object's longer side: 1 − 2·border_ratio of ops/intake/prepare.py.
FRAME_FILL = 0.8
REFERENCE_FOV_DEG = 40.0
REFERENCE_DISTANCE = 2.5
NORMALISE_SIZE = 256  # the resolution the frame is fitted (and tested) at
MAX_EXTENT = 0.95  # every vertex stays inside the reconstruction grid's ±1 with a margin


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


def normalise(mesh: TexturedMesh, iterations: int = 6) -> TexturedMesh:
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
