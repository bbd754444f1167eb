"""Mesh health (weight-free QA): topology, UV coverage, texel density and UV-seam colour leakage of a
(textured) triangle mesh, all in one ``mesh_health`` report.

Arguments are checked as in ``morpheus_core.metrics.image``: a wrong shape or dtype, or NaN/Inf values,
raise its ``MetricInputError`` naming the argument.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from morpheus_core.metrics.image import MetricInputError

if TYPE_CHECKING:
    from numpy.typing import ArrayLike


# Faces with area below this fraction of the squared bounding-box diagonal count as degenerate:
# scale-free, and far below any triangle a renderer would draw at a sensible resolution.
_DEGENERATE_REL_AREA = 1e-12
# UVs of one welded vertex on the two faces of an edge closer than this are the same UV (no seam).
_UV_SEAM_TOL = 1e-6
# Default UV raster size when no texture is given to measure coverage at.
_DEFAULT_UV_RESOLUTION = 512


def _array(a: ArrayLike | Tensor, name: str, dtype: type, cols: int) -> np.ndarray:
    if isinstance(a, Tensor):
        a = a.detach().cpu().numpy()
    arr = np.asarray(a)
    if arr.ndim != 2 or arr.shape[1] != cols:
        raise MetricInputError(f"{name} must have shape (N, {cols}), got {arr.shape}")
    if dtype is np.int64:
        if arr.size and not np.issubdtype(arr.dtype, np.integer):
            raise MetricInputError(f"{name} must hold integers, got {arr.dtype}")
        return arr.astype(np.int64)
    if not np.issubdtype(arr.dtype, np.floating) and arr.size:
        raise MetricInputError(f"{name} must be floating point, got {arr.dtype}")
    arr = arr.astype(np.float64)
    if not np.isfinite(arr).all():
        raise MetricInputError(f"{name} holds NaN/Inf values")
    return arr


def _texture(texture: ArrayLike | Tensor) -> np.ndarray:
    if isinstance(texture, Tensor):
        texture = texture.detach().cpu().numpy()
    tex = np.asarray(texture)
    if tex.ndim != 3 or tex.shape[2] != 3 or tex.shape[0] == 0 or tex.shape[1] == 0:
        raise MetricInputError(f"texture must have shape (H, W, 3), got {tex.shape}")
    if tex.dtype == np.uint8:
        return tex.astype(np.float64) / 255.0
    if not np.issubdtype(tex.dtype, np.floating):
        raise MetricInputError(f"texture must be float in [0, 1] or uint8, got {tex.dtype}")
    tex = tex.astype(np.float64)
    if not np.isfinite(tex).all():
        raise MetricInputError("texture holds NaN/Inf values")
    return tex


def _uv_raster(uvs: np.ndarray, faces: np.ndarray, height: int, width: int) -> int:
    """Number of texels whose centre lies in at least one UV triangle (row 0 at v = 1)."""
    from morpheus_core.render.raster import rasterize

    uv = torch.from_numpy(uvs)
    # Orthographic UV "camera": NDC x = 2u − 1, y = 2v − 1, so image row 0 is v = 1 as in the bake.
    clip = torch.cat([uv * 2 - 1, torch.zeros_like(uv[:, :1]), torch.ones_like(uv[:, :1])], dim=1)
    frags = rasterize(clip, torch.from_numpy(faces), height, width)
    return int((frags.face_id >= 0).sum())


def _bilinear(tex: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear texture lookup at uv (..., 2), v up, texel centres at ((j + ½)/W, 1 − (i + ½)/H), clamped."""
    h, w = tex.shape[:2]
    x = np.clip(uv[..., 0] * w - 0.5, 0.0, w - 1.0)
    y = np.clip((1.0 - uv[..., 1]) * h - 0.5, 0.0, h - 1.0)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    top = tex[y0, x0] * (1 - fx) + tex[y0, x1] * fx
    bottom = tex[y1, x0] * (1 - fx) + tex[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def _seams(faces: np.ndarray, welded: np.ndarray, uvs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """UV seams: 3-D edges (by welded position) shared by exactly two faces whose UVs there differ.

    Returns the UV end points of both sides stacked as (2, S, 2 ends, 2), ordered alike (side B's
    ends are matched to side A's by position, whatever the faces' winding), and the original vertex
    ids of side A's ends (S, 2) for edge lengths. Boundary and non-manifold edges are not seams."""
    corner_a = faces.reshape(-1)
    corner_b = faces[:, [1, 2, 0]].reshape(-1)
    wa, wb = welded[faces].reshape(-1), welded[faces[:, [1, 2, 0]]].reshape(-1)
    proper = wa != wb
    corner_a, corner_b, wa, wb = corner_a[proper], corner_b[proper], wa[proper], wb[proper]
    lo, hi = np.minimum(wa, wb), np.maximum(wa, wb)
    keys = lo * (int(welded.max()) + 1) + hi
    order = np.argsort(keys, kind="stable")
    keys = keys[order]
    _, start, counts = np.unique(keys, return_index=True, return_counts=True)
    pairs = start[counts == 2]
    first, second = order[pairs], order[pairs + 1]
    a0, a1 = corner_a[first], corner_b[first]
    b0, b1 = corner_a[second], corner_b[second]
    # Align side B to side A: its corner at A's first welded position goes first.
    flip = welded[b0] != welded[a0]
    b0, b1 = np.where(flip, b1, b0), np.where(flip, b0, b1)
    uv_a = np.stack([uvs[a0], uvs[a1]], axis=1)
    uv_b = np.stack([uvs[b0], uvs[b1]], axis=1)
    seam = np.abs(uv_a - uv_b).max(axis=(1, 2)) > _UV_SEAM_TOL
    return np.stack([uv_a[seam], uv_b[seam]]), np.stack([a0[seam], a1[seam]], axis=1)


def _seam_leakage(vertices: np.ndarray, faces: np.ndarray, welded: np.ndarray, uvs: np.ndarray,
                  tex: np.ndarray, samples: int = 4) -> tuple[float, int]:
    """Length-weighted mean absolute colour difference between the two sides of every UV seam."""
    (uv_a, uv_b), ends = _seams(faces, welded, uvs)
    if len(ends) == 0:
        return 0.0, 0
    # Interior points only: the corners are shared with other seams and would be counted twice.
    t = (np.arange(samples, dtype=np.float64) + 1.0) / (samples + 1.0)
    pts_a = uv_a[:, :1] * (1 - t[None, :, None]) + uv_a[:, 1:] * t[None, :, None]
    pts_b = uv_b[:, :1] * (1 - t[None, :, None]) + uv_b[:, 1:] * t[None, :, None]
    diff = np.abs(_bilinear(tex, pts_a) - _bilinear(tex, pts_b)).mean(axis=(1, 2))
    length = np.linalg.norm(vertices[ends[:, 0]] - vertices[ends[:, 1]], axis=1)
    if length.sum() <= 0:
        return float(diff.mean()), len(ends)
    return float((diff * length).sum() / length.sum()), len(ends)


def mesh_health(vertices: ArrayLike | Tensor, faces: ArrayLike | Tensor, uvs: ArrayLike | Tensor | None = None,
                texture: ArrayLike | Tensor | None = None, *,
                uv_resolution: int = _DEFAULT_UV_RESOLUTION) -> dict[str, float | int | bool | None]:
    """Topology, UV and texture health of a (textured) triangle mesh.

    ``vertices`` (V, 3) float, ``faces`` (F, 3) int, ``uvs`` (V, 2) per vertex with v up, ``texture``
    (H, W, 3) float in [0, 1] (or uint8) with row 0 at v = 1 — the layout ``export.uv_bake.bake_uv`` writes.
    Topology is measured on vertices welded by position (trimesh's 1e-8 merge precision), because UV
    seams split vertices that are one point of the surface:

    * ``faces``, ``vertices``: the counts as given; ``components``: edge-connected face components;
    * ``watertight``: every welded edge has exactly two faces; ``winding_consistent``: trimesh's check;
    * ``euler_number``: V − E + F of the welded mesh (2 for a closed sphere-like surface);
    * ``degenerate_faces``: faces with area ≤ 1e-12 × (bounding-box diagonal)², repeated corners included;
    * ``surface_area``: total 3-D area;
    * ``uv_coverage``: fraction of texels (at the texture's size, else ``uv_resolution``²) whose centre
      lies inside at least one UV triangle — rasterised, so overlapping charts count once. The cost
      grows with the summed UV area in texels: under a second for a packed 20k-face atlas at 1024²,
      but F·H·W for F triangles that each span the whole square;
    * ``texel_density``: sqrt(covered texels / surface area), texels per world unit along the surface
      (uniform parametrisation assumed; stacked charts lower it since they share texels). Needs a
      texture; None without one or with zero area;
    * ``seam_edges``, ``seam_leakage``: 3-D edges shared by two faces whose UVs differ there, and the
      mean absolute colour difference (over RGB, 0–1 scale) between the texture sampled bilinearly at
      4 interior points along the edge in each face's UV, weighted by 3-D edge length. 0.0 with no seams
      or no texture (nothing can leak); None without UVs.

    A mesh with no faces gives faces 0, its vertex count, watertight False and None for the rest.
    """
    verts = _array(vertices, "vertices", np.float64, 3)
    tris = _array(faces, "faces", np.int64, 3)
    nv, nf = len(verts), len(tris)
    if nf and (tris.min() < 0 or tris.max() >= nv):
        raise MetricInputError(f"faces index vertices outside [0, {nv}): [{tris.min()}, {tris.max()}]")
    uv = _array(uvs, "uvs", np.float64, 2) if uvs is not None else None
    if uv is not None and len(uv) != nv:
        raise MetricInputError(f"uvs must have one row per vertex ({nv}), got {len(uv)}")
    tex = _texture(texture) if texture is not None else None
    if not isinstance(uv_resolution, int) or uv_resolution < 1:
        raise MetricInputError(f"uv_resolution must be a positive integer, got {uv_resolution!r}")

    report: dict[str, float | int | bool | None] = {
        "faces": nf, "vertices": nv, "components": None, "watertight": False, "winding_consistent": None,
        "euler_number": None, "degenerate_faces": None, "surface_area": None, "uv_coverage": None,
        "texel_density": None, "seam_edges": None, "seam_leakage": None,
    }
    if nf == 0:
        return report

    import trimesh

    # Weld only the referenced vertices, so stray points neither join components nor shift V − E + F.
    used = np.unique(tris)
    _, inverse = trimesh.grouping.unique_rows(verts[used])
    welded = np.full(nv, -1, dtype=np.int64)
    welded[used] = inverse
    unique_pos = np.zeros((int(inverse.max()) + 1, 3))
    unique_pos[inverse] = verts[used]
    mesh = trimesh.Trimesh(unique_pos, welded[tris], process=False, validate=False)

    labels = trimesh.graph.connected_components(mesh.face_adjacency, nodes=np.arange(nf), min_len=1)
    corners = verts[tris]
    areas = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    diagonal_sq = float(np.sum((verts[used].max(axis=0) - verts[used].min(axis=0)) ** 2))
    repeated = (tris[:, 0] == tris[:, 1]) | (tris[:, 1] == tris[:, 2]) | (tris[:, 0] == tris[:, 2])
    degenerate = repeated | (areas <= _DEGENERATE_REL_AREA * diagonal_sq)
    surface = float(areas.sum())
    report.update({
        "components": len(labels), "watertight": bool(mesh.is_watertight),
        "winding_consistent": bool(mesh.is_winding_consistent), "euler_number": int(mesh.euler_number),
        "degenerate_faces": int(degenerate.sum()), "surface_area": surface,
    })
    if uv is None:
        return report

    height, width = tex.shape[:2] if tex is not None else (uv_resolution, uv_resolution)
    covered = _uv_raster(uv, tris, height, width)
    report["uv_coverage"] = covered / (height * width)
    if tex is not None and surface > 0:
        report["texel_density"] = math.sqrt(covered / surface)
    if tex is None:
        _, ends = _seams(tris, welded, uv)
        report["seam_edges"], report["seam_leakage"] = len(ends), 0.0
    else:
        leak, count = _seam_leakage(verts, tris, welded, uv, tex)
        report["seam_edges"], report["seam_leakage"] = count, leak
    return report
