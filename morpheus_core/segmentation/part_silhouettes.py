"""Silhouette parts: how many separate pieces a mask shows, and whether one stack of silhouettes
lost a piece that another shows (the mesh against the NeRF it came from).

A fixed density iso-level drops thin parts of a NeRF (DESIGN.md §4: the vase loses its neck),
and a global silhouette IoU barely notices: a lost mug handle costs a few per cent of the area.
So the comparison looks for the largest *connected* region that the reference shows and the
candidate does not, per view, after a small morphological opening — one or two pixels of
disagreement all along the outline form a ring that is connected but is not a part.

Pixels are 8-connected, so a thin diagonal stroke stays one part.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from morpheus_core.cameras import Cameras, OrbitConfig, orbit
from morpheus_core.geometry.mesh_hygiene import connected_labels
from morpheus_core.geometry.nerf import NerfField
from morpheus_core.render.textured import TexturedMesh, render_textured
from morpheus_core.render.volume import OccupancyGrid, render_silhouette

_NEIGHBOURS = ((0, 1), (1, -1), (1, 0), (1, 1))  # half of the 8-neighbourhood: each pair once


def _as_masks(masks: Tensor, name: str) -> Tensor:
    """(N, H, W) bool from (H, W), (N, H, W) or (N, 1, H, W) bool or {0, 1}-valued tensors."""
    m = torch.as_tensor(masks)
    if m.dim() == 4 and m.shape[1] == 1:
        m = m[:, 0]
    if m.dim() == 2:
        m = m[None]
    if m.dim() != 3:
        raise ValueError(f"{name} must be (H, W), (N, H, W) or (N, 1, H, W), got {tuple(m.shape)}")
    return m.bool() if m.dtype == torch.bool else m > 0.5


def mask_components(mask: Tensor) -> tuple[Tensor, Tensor]:
    """8-connected components of one (H, W) mask (bool, or > 0.5): labels (H, W) int64 with −1 off
    the mask and 0…K−1 on it (0 the largest), and each component's pixel count (K,)."""
    m = _as_masks(mask, "mask")
    if m.shape[0] != 1:
        raise ValueError(f"mask_components takes one mask, got {m.shape[0]}")
    on = m[0].cpu().numpy()
    h, w = on.shape
    index = np.full((h, w), -1, dtype=np.int64)
    index[on] = np.arange(int(on.sum()))
    pairs = []
    for dy, dx in _NEIGHBOURS:  # pixel pairs (y, x) ~ (y + dy, x + dx), both inside the image
        xs_a, xs_b = (slice(0, w - dx), slice(dx, w)) if dx >= 0 else (slice(-dx, w), slice(0, w + dx))
        a, b = index[: h - dy, xs_a], index[dy:, xs_b]
        both = (a >= 0) & (b >= 0)
        pairs.append(np.stack([a[both], b[both]], 1))
    labels = connected_labels(int(on.sum()), np.concatenate(pairs))
    sizes = np.bincount(labels, minlength=int(labels.max()) + 1 if len(labels) else 0)
    rank = np.lexsort((np.arange(len(sizes)), -sizes))
    relabel = np.empty_like(rank)
    relabel[rank] = np.arange(len(rank))
    out = np.full((h, w), -1, dtype=np.int64)
    out[on] = relabel[labels]
    return torch.from_numpy(out), torch.from_numpy(sizes[rank])


def count_parts(mask: Tensor, min_share: float = 0.01) -> int:
    """Components of ``mask`` (H, W) holding at least ``min_share`` of its area: segmentation specks
    are not parts of the object."""
    if not 0.0 <= min_share <= 1.0:
        raise ValueError(f"min_share must lie in [0, 1], got {min_share}")
    _, sizes = mask_components(mask)
    total = int(sizes.sum())
    return int((sizes >= min_share * total).sum()) if total else 0


def open_masks(masks: Tensor, radius: int) -> Tensor:
    """Morphological opening of (N, H, W) bool masks by a (2r+1)² square: removes strokes thinner
    than 2r + 1 pixels, keeps the rest at its size."""
    if radius <= 0:
        return masks
    x = masks.float()[:, None]
    k = 2 * radius + 1
    eroded = -F.max_pool2d(-x, k, stride=1, padding=radius)  # pixels outside the image count as on
    return (F.max_pool2d(eroded, k, stride=1, padding=radius)[:, 0] > 0.5) & masks


@dataclass(frozen=True)
class PartComparison:
    """Per view: ``iou`` of the two silhouettes and ``missing_share``, the area of the largest
    connected region the reference shows and the candidate lacks (after the opening) over the
    reference silhouette's area."""

    iou: tuple[float, ...]
    missing_share: tuple[float, ...]

    @property
    def iou_min(self) -> float:
        return min(self.iou)

    @property
    def iou_mean(self) -> float:
        return sum(self.iou) / len(self.iou)

    @property
    def missing_share_max(self) -> float:
        return max(self.missing_share)


def dilate_masks(masks: Tensor, radius: int) -> Tensor:
    """(N, H, W) bool masks grown by a (2r+1)² square."""
    if radius <= 0:
        return masks
    return F.max_pool2d(masks.float()[:, None], 2 * radius + 1, stride=1, padding=radius)[:, 0] > 0.5


def compare_part_silhouettes(reference: Tensor, candidate: Tensor, opening: int = 1,
                             margin: int = 0) -> PartComparison:
    """Compare two stacks of silhouettes of the same views ((N, H, W) or (N, 1, H, W), bool or
    > 0.5). ``margin`` > 0: what the reference shows within that many pixels of the candidate
    does not count as missing (a candidate uniformly thinner by up to ``margin`` px lost no part);
    the IoU is always of the silhouettes as given. A view where both are empty counts as IoU 1
    with nothing missing; where only the reference is empty, IoU 0 (the candidate shows
    something that is not there)."""
    ref, cand = _as_masks(reference, "reference"), _as_masks(candidate, "candidate")
    if ref.shape != cand.shape:
        raise ValueError(f"reference and candidate differ in shape: {tuple(ref.shape)} vs {tuple(cand.shape)}")
    if ref.shape[0] == 0:
        raise ValueError("need at least one view to compare")
    ref, cand = ref.cpu(), cand.cpu()
    missing = open_masks(ref & ~dilate_masks(cand, margin), opening)
    ious, shares = [], []
    for r, c, m in zip(ref, cand, missing, strict=True):
        union, area = int((r | c).sum()), int(r.sum())
        ious.append(int((r & c).sum()) / union if union else 1.0)
        largest = int(mask_components(m)[1][0]) if bool(m.any()) else 0
        shares.append(largest / area if area else 0.0)
    return PartComparison(tuple(ious), tuple(shares))


# The NeRF against the exported mesh (the qa stage's ``parts_kept``): silhouettes from a few novel views.
SILHOUETTE_LEVEL = 0.5


def part_cameras(n: int, elevation_deg: float) -> Cameras:
    """``n`` azimuths evenly around the object, offset by half a step from the reference view (0°),
    which the photo's mask already judges."""
    azim = (torch.arange(n, dtype=torch.float64) + 0.5) * (360.0 / n)
    azim = torch.where(azim > 180.0, azim - 360.0, azim).float()
    cfg = OrbitConfig()  # the turntable's cameras: same distance and field of view
    return orbit(elevation_deg, azim, cfg.distance, cfg.fov_deg, cfg.near, cfg.far)


def nerf_silhouettes(nerf: NerfField, occupancy: OccupancyGrid | None, cameras: Cameras, resolution: int,
                     n_samples: int) -> Tensor:
    """(N, H, W) bool: the NeRF's opacity above one half."""
    return render_silhouette(nerf, cameras, resolution, resolution, n_samples, occupancy, SILHOUETTE_LEVEL).cpu()


@torch.no_grad()
def asset_silhouettes(asset: TexturedMesh, cameras: Cameras, resolution: int) -> Tensor:
    """(N, H, W) bool: the GLB's rendered opacity above one half."""
    return render_textured(asset, cameras, resolution, resolution).opacity[..., 0].float().cpu() > SILHOUETTE_LEVEL
