"""NeRF → DMTet without losing thin parts: a box-filtered occupancy, an iso-level chosen by silhouettes.

A fixed density iso-level (25 in the official config) drops thin parts of small or short-trained
fields: a neck or handle thinner than a grid cell falls between the vertices, and a part whose
density stays below the level vanishes although the NeRF renders it opaque. Two changes keep them:

* **occupancy, box-filtered**: at each grid vertex the opacity of a cell-thick slab,
  ``1 − exp(−σ·cell)``, averaged over a 3×3×3 stencil spanning the vertex's cell. A part narrower
  than a cell still reaches the nearest vertices' averages, and the values lie in [0, 1] whatever
  the density scale of the field;
* **iso-level from the field itself**: every candidate level is meshed and its silhouettes are
  compared with the NeRF's own (opacity > ½) from the reference view and a ring of views; the level
  with the best mean IoU wins. The same silhouettes are the check that is recorded before
  optimising, and they stay available to the DMTet stage as the NeRF's geometry.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import torch
from torch import Tensor

from morpheus_core.cameras import Cameras, orbit
from morpheus_core.geometry.marching_tets import EmptySurfaceError
from morpheus_core.geometry.nerf import RadianceField
from morpheus_core.geometry.tet_surface import DMTet
from morpheus_core.render.mesh_renderer import MeshRenderConfig, render_mesh
from morpheus_core.render.volume import OccupancyGrid, VolumeRenderConfig, render_volume


@dataclass(frozen=True)
class ConversionConfig:
    """NeRF → DMTet: the occupancy iso-levels tried and the silhouette views that choose among them."""

    levels: tuple[float, ...] = (0.05, 0.1, 0.2, 0.35, 0.5, 0.65, 0.8)
    """Box-filtered occupancy iso-levels in (0, 1) tried; the best mean silhouette IoU wins (ties: lower)."""
    ring_views: int = 6
    """Check views evenly spaced in azimuth at each of ``elevations``, besides the reference view."""
    elevations: tuple[float, ...] = (25.0, -20.0)
    """Elevations (degrees) of the rings of check views."""
    resolution: int = 64
    """Size (px) of the check views' NeRF and mesh silhouettes."""
    samples: int = 96
    """Samples per ray of the NeRF silhouette renders (unstratified)."""
    chunk_points: int = 1 << 18
    """Points per NeRF density call while filtering and rendering: bounds peak memory, not the result."""

    def __post_init__(self) -> None:
        if not self.levels or not all(0.0 < v < 1.0 for v in self.levels):
            raise ValueError(f"occupancy levels must lie in (0, 1), got {self.levels}")
        if self.ring_views < 1 or self.resolution < 8 or self.samples < 1:
            raise ValueError("ring_views must be ≥ 1, resolution ≥ 8 and samples ≥ 1")


@dataclass(frozen=True)
class Silhouettes:
    """The NeRF's opacity (V×H×W in [0, 1]) from ``cameras``; view 0 is the reference view."""

    cameras: Cameras
    opacity: Tensor


@dataclass(frozen=True)
class Conversion:
    """The chosen level, the mean silhouette IoU per tried level, and the NeRF's silhouettes."""

    level: float
    iou: float
    ious: dict[float, float]
    silhouettes: Silhouettes


def check_cameras(cfg: ConversionConfig) -> Cameras:
    """The reference view (0°, 0°) then ``ring_views`` azimuths at each elevation."""
    n = cfg.ring_views
    azim = [0.0] + [a * 360.0 / n - 180.0 for _ in cfg.elevations for a in range(n)]
    elev = [0.0] + [e for e in cfg.elevations for _ in range(n)]
    return orbit(torch.tensor(elev), torch.tensor(azim))


def _stencil(cell: float, device: torch.device) -> Tensor:
    offsets = [(-cell / 3, 0.0, cell / 3)] * 3
    return torch.tensor(list(itertools.product(*offsets)), dtype=torch.float32, device=device)


@torch.no_grad()
def box_occupancy(nerf: RadianceField, points: Tensor, cell: float, chunk_points: int = 1 << 18) -> Tensor:
    """Mean over a 3×3×3 stencil (spacing cell/3) around each point of ``1 − exp(−σ·cell)``."""
    stencil = _stencil(cell, points.device)
    per_chunk = max(1, chunk_points // len(stencil))
    out = []
    for part in points.split(per_chunk):
        sigma = nerf.density((part[:, None, :] + stencil).reshape(-1, 3)).float().reshape(len(part), -1)
        sigma = torch.nan_to_num(sigma, nan=0.0, posinf=1e6).clamp_min(0.0)
        out.append((1.0 - torch.exp(-sigma * cell)).mean(dim=1))
    return torch.cat(out)


@torch.no_grad()
def nerf_silhouettes(nerf: RadianceField, cameras: Cameras, cfg: ConversionConfig, device: torch.device,
                     occupancy: OccupancyGrid | None = None) -> Silhouettes:
    render = VolumeRenderConfig(n_samples=cfg.samples, stratified=False, with_normals=False,
                                chunk_points=cfg.chunk_points)
    cams = cameras.to(device)
    out = render_volume(nerf, cams, cfg.resolution, cfg.resolution, render, 1.0, occupancy)
    return Silhouettes(cams, out.opacity.squeeze(-1).float())


def silhouette_iou(a: Tensor, b: Tensor) -> Tensor:
    """IoU per view of two V×H×W opacity stacks, each thresholded at ½ (1 where both are empty)."""
    a, b = a > 0.5, b > 0.5
    inter = (a & b).flatten(1).sum(1).float()
    union = (a | b).flatten(1).sum(1).float()
    return torch.where(union > 0, inter / union.clamp_min(1.0), torch.ones_like(union))


@torch.no_grad()
def mesh_silhouettes(dmtet: DMTet, silhouettes: Silhouettes, resolution: int) -> Tensor:
    mesh = dmtet()
    # Hard silhouettes: anti-aliasing only matters for gradients, and this is a no-grad check.
    out = render_mesh(mesh, silhouettes.cameras, resolution, resolution, lambda p: torch.zeros_like(p),
                      config=MeshRenderConfig(antialias=False))
    return out.opacity.squeeze(-1).float()


@torch.no_grad()
def convert(dmtet: DMTet, nerf: RadianceField, cfg: ConversionConfig,
            occupancy: OccupancyGrid | None = None) -> Conversion:
    """Initialise ``dmtet``'s SDF from ``nerf`` at the occupancy level whose mesh matches the NeRF's
    silhouettes best (ties: the lower level, which keeps more of thin parts)."""
    values = box_occupancy(nerf, dmtet.grid_vertices, dmtet.config.cell_size, cfg.chunk_points)
    silhouettes = nerf_silhouettes(nerf, check_cameras(cfg), cfg, dmtet.sdf.device, occupancy)
    ious: dict[float, float] = {}
    for level in sorted(cfg.levels):
        try:
            dmtet.init_from_values(values, level)
            mesh_alpha = mesh_silhouettes(dmtet, silhouettes, cfg.resolution)
        except EmptySurfaceError:
            continue
        ious[level] = float(silhouette_iou(mesh_alpha, silhouettes.opacity).mean())
    if not ious:
        raise EmptySurfaceError(f"no occupancy level in {cfg.levels} gives a surface (max occupancy "
                                f"{float(values.max()):.3g}): the NeRF is empty — check the NeRF stage")
    best = max(ious, key=lambda lv: (round(ious[lv], 6), -lv))
    dmtet.init_from_values(values, best)
    return Conversion(best, ious[best], ious, silhouettes)
