"""What the QA stage's ``parts_kept`` check measures: the GLB's silhouettes against the NeRF's from
a few novel views (``morpheus_core.part_silhouettes`` compares them).

The NeRF is what the photo and the prior agreed on before DMTet's fixed iso-level and floater
removal; where it is opaque and the mesh is not, from any side, the mesh lost a part.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor

from morpheus_core.cameras import Cameras, OrbitConfig, orbit
from morpheus_core.geometry.nerf import NerfField
from morpheus_core.part_silhouettes import PartComparison, compare_part_silhouettes
from morpheus_core.render.textured import TexturedMesh, render_textured
from morpheus_core.render.volume import OccupancyGrid, render_silhouette
from ops.stages.nerf import NERF_FILE, load_nerf

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


def compare_with_nerf(asset: TexturedMesh, nerf_dir: Path | None, views: int, resolution: int, n_samples: int,
                      elevation_deg: float, opening: int, margin: int, device: torch.device) -> PartComparison | None:
    """The GLB against the NeRF from ``views`` novel views; None when there is no NeRF output (an
    asset refined from an existing mesh has no NeRF stage)."""
    if nerf_dir is None or not (Path(nerf_dir) / NERF_FILE).is_file():
        return None
    nerf, occupancy = load_nerf(Path(nerf_dir), device)
    cameras = part_cameras(views, elevation_deg).to(device)
    reference = nerf_silhouettes(nerf, occupancy, cameras, resolution, n_samples)
    return compare_part_silhouettes(reference, asset_silhouettes(asset, cameras, resolution), opening, margin)
