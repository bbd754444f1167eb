"""The textured mesh the bake produces and every exporter and the textured renderer read."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class BakedTexture:
    """An unwrapped, textured mesh ready for export. Vertices are split along UV seams.

    ``uvs`` (N, 2) with v up; ``texture`` (S, S, 3) uint8 with row 0 at v = 1; ``normals`` (N, 3)
    smooth normals of the source mesh (continuous across seams); ``coverage``: fraction of texels
    covered by charts; ``source_faces``: faces before any decimation."""

    vertices: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray
    normals: np.ndarray
    texture: np.ndarray
    coverage: float
    source_faces: int
