"""Geometry against a known truth: visible-surface points from depth maps, Chamfer distance, F-score.

Points come from renders rather than from the meshes' surfaces so that a NeRF (no mesh), a mesh
and a ground truth assembled from intersecting parts are measured alike: only surface a camera can
see counts, and faces buried inside another part (a mug handle's ends) do not.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from morpheus_core.cameras import Cameras
from morpheus_core.metrics.image import MetricInputError
from morpheus_core.render.output import RenderOutput

# Pairwise distances are taken in blocks of this many query points (memory, not speed).
_BLOCK = 4096


def visible_points(render: RenderOutput, cameras: Cameras, min_opacity: float = 0.5,
                   weighted_depth: bool = False) -> Tensor:
    """World-space points of the surface seen in ``render``: each pixel with opacity ≥ ``min_opacity``
    put on its camera ray at its depth, (N, 3) over all views.

    Mesh renders store the hit distance; volume renders store Σ wᵢtᵢ, the distance weighted by
    opacity, which ``weighted_depth=True`` divides back out."""
    if not 0.0 < min_opacity <= 1.0:
        raise MetricInputError(f"min_opacity must lie in (0, 1], got {min_opacity}")
    b, h, w, _ = render.depth.shape
    if len(cameras) != b:
        raise MetricInputError(f"{b} rendered views but {len(cameras)} cameras")
    origins, dirs = cameras.to(device=render.depth.device).rays(h, w)
    opacity, depth = render.opacity.float(), render.depth.float()
    if weighted_depth:
        depth = depth / opacity.clamp_min(1e-6)
    keep = (opacity[..., 0] >= min_opacity) & (depth[..., 0] > 0) & torch.isfinite(depth[..., 0])
    points = origins.float() + dirs.float() * depth
    return points[keep]


@dataclass(frozen=True)
class SurfaceDistance:
    """``chamfer``: the mean of the two directed mean nearest-neighbour distances (world units);
    ``precision``: share of predicted points within ``threshold`` of the truth; ``recall``: share
    of true points within it of the prediction; ``fscore``: their harmonic mean."""

    chamfer: float
    precision: float
    recall: float
    fscore: float
    threshold: float


def _nearest(query: Tensor, points: Tensor) -> Tensor:
    # The matmul form of cdist leaves ~1e-5 of rounding on identical points; exact here is cheap.
    exact = "donot_use_mm_for_euclid_dist"
    return torch.cat([torch.cdist(query[i:i + _BLOCK], points, compute_mode=exact).min(dim=1).values
                      for i in range(0, query.shape[0], _BLOCK)])


def _subsample(points: Tensor, count: int, generator: torch.Generator) -> Tensor:
    if points.shape[0] <= count:
        return points
    return points[torch.randperm(points.shape[0], generator=generator)[:count].to(points.device)]


def surface_distance(predicted: Tensor, truth: Tensor, threshold: float, max_points: int = 20000,
                     seed: int = 0) -> SurfaceDistance:
    """Chamfer distance and F-score at ``threshold`` between two point sets (N, 3) and (M, 3).

    Sets larger than ``max_points`` are subsampled (seeded) first. Raises ``MetricInputError`` for
    an empty or non-finite set: a reconstruction with no visible surface has no distance."""
    if not threshold > 0:
        raise MetricInputError(f"threshold must be > 0, got {threshold}")
    for name, pts in (("predicted", predicted), ("truth", truth)):
        if pts.dim() != 2 or pts.shape[-1] != 3:
            raise MetricInputError(f"{name} points must be (N, 3), got {tuple(pts.shape)}")
        if pts.shape[0] == 0:
            raise MetricInputError(f"{name} points are empty: nothing visible to measure")
        if not bool(torch.isfinite(pts).all()):
            raise MetricInputError(f"{name} points hold NaN or Inf")
    generator = torch.Generator().manual_seed(seed)
    p = _subsample(predicted.double(), max_points, generator)
    t = _subsample(truth.double(), max_points, generator)
    d_pt, d_tp = _nearest(p, t), _nearest(t, p)
    precision = float((d_pt <= threshold).double().mean())
    recall = float((d_tp <= threshold).double().mean())
    fscore = 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)
    return SurfaceDistance(0.5 * (float(d_pt.mean()) + float(d_tp.mean())), precision, recall, fscore, threshold)
