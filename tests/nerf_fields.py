"""Small NeRF fields and their occupancy grids for the volume-rendering tests (CPU and CUDA alike)."""

from __future__ import annotations

import torch

from morpheus_core.geometry.hashgrid import HashGridConfig
from morpheus_core.geometry.nerf import NerfConfig, NerfField
from morpheus_core.render.volume import OccupancyGrid, OccupancyGridConfig


def small_nerf(seed: int = 0) -> NerfField:
    """A randomly initialised NeRF field small enough for CPU tests (4 hash-grid levels, 16 hidden units)."""
    grid = HashGridConfig(n_levels=4, log2_table_size=12, base_resolution=8, per_level_scale=1.6)
    return NerfField(NerfConfig(grid=grid, hidden=16), generator=torch.Generator().manual_seed(seed))


def occupancy_grid_for(field: NerfField, device: torch.device, seed: int) -> OccupancyGrid:
    """A 16³ occupancy grid on ``device``, refreshed once from ``field`` (its samples drawn from ``seed``)."""
    grid = OccupancyGrid(OccupancyGridConfig(resolution=16, density_threshold=1e-3), field.bbox_radius).to(device)
    grid.refresh(field, torch.Generator().manual_seed(seed))
    return grid
