"""NeRF → DMTet: the box-filtered occupancy and the silhouette-chosen iso-level keep thin parts."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from torch import Tensor

from morpheus_core.geometry.marching_tets import EmptySurfaceError
from morpheus_core.geometry.nerf import FieldSample
from morpheus_core.geometry.tet_surface import DMTet, DMTetConfig
from morpheus_core.nerf_to_dmtet import (
    ConversionConfig,
    box_occupancy,
    check_cameras,
    convert,
    mesh_silhouettes,
    silhouette_iou,
)

GRID = 32
CELL = 2.0 / GRID
FAST = ConversionConfig(ring_views=4, elevations=(20.0,), resolution=48, samples=64)


class VaseField:
    """A dense body (sphere) with a neck: a vertical cylinder two grid cells wide whose density is
    low (a thin part of a short-trained NeRF) but which still renders nearly opaque."""

    bbox_radius = 1.0

    def __init__(self, body_density: float = 200.0, neck_density: float = 18.0, neck_radius: float = CELL,
                 offset: Tensor | None = None) -> None:
        self.body_density, self.neck_density, self.neck_radius = body_density, neck_density, neck_radius
        self.offset = offset if offset is not None else torch.zeros(3)

    def density(self, points: Tensor) -> Tensor:
        p = points - self.offset.to(points)
        body = (p.norm(dim=-1) < 0.35).float() * self.body_density
        radial = p[:, [0, 2]].norm(dim=-1)
        neck = ((radial < self.neck_radius) & (p[:, 1] > 0.0) & (p[:, 1] < 0.75)).float() * self.neck_density
        return torch.maximum(body, neck)

    def query(self, points: Tensor, with_normals: bool = False) -> FieldSample:
        return FieldSample(self.density(points), torch.full_like(points, 0.5), None)


def _dmtet(cache_dir: Path) -> DMTet:
    return DMTet(DMTetConfig(resolution=GRID), cache_dir=cache_dir)


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("tets")


def _neck_kept(dmtet: DMTet, field: VaseField) -> bool:
    v = dmtet().vertices - field.offset
    return bool(((v[:, 1] > 0.6) & (v[:, [0, 2]].norm(dim=-1) < 3 * CELL)).any())


def test_a_neck_two_cells_wide_survives_the_conversion(cache_dir: Path) -> None:
    # A fresh offset each run: the neck's position against the grid vertices is not a lucky one.
    offset = (torch.rand(3, generator=torch.Generator().manual_seed(int(torch.randint(0, 2**31, ())))) - 0.5) * CELL
    field = VaseField(offset=offset)
    fixed = _dmtet(cache_dir)
    fixed.init_from_density(field.density, 25.0)  # the official fixed level loses the neck
    assert not _neck_kept(fixed, field)

    dmtet = _dmtet(cache_dir)
    result = convert(dmtet, field, FAST)
    assert _neck_kept(dmtet, field), f"neck lost at level {result.level} (IoUs {result.ious})"
    assert result.iou > 0.85 and result.level in FAST.levels
    assert result.ious[result.level] == max(result.ious.values())
    # The chosen mesh is what the check measured.
    again = silhouette_iou(mesh_silhouettes(dmtet, result.silhouettes, FAST.resolution), result.silhouettes.opacity)
    assert float(again.mean()) == pytest.approx(result.iou, abs=1e-6)


def test_box_occupancy_is_bounded_and_sees_parts_between_vertices() -> None:
    field = VaseField(neck_density=1e9, neck_radius=0.3 * CELL)  # thinner than a cell, extreme density
    # A vertex half a cell from the neck's axis: the neck passes between vertices.
    points = torch.tensor([[0.5 * CELL, 0.4, 0.0], [0.5, -0.6, 0.5], [0.0, 0.0, 0.0]])
    occ = box_occupancy(field, points, CELL)
    assert torch.isfinite(occ).all() and bool(((occ >= 0) & (occ <= 1)).all())
    assert 0.0 < float(occ[0]) < 1.0  # point sampling at the vertex alone would give exactly 0
    assert float(occ[1]) == 0.0 and float(occ[2]) == pytest.approx(1.0, abs=1e-4)


def test_silhouette_iou_per_view() -> None:
    g = torch.Generator().manual_seed(int(torch.randint(0, 2**31, ())))
    a = (torch.rand(3, 16, 16, generator=g) > 0.5).float()
    assert torch.allclose(silhouette_iou(a, a), torch.ones(3))
    assert float(silhouette_iou(a, 1.0 - a).max()) == 0.0
    assert float(silhouette_iou(torch.zeros(1, 4, 4), torch.zeros(1, 4, 4))) == 1.0


def test_check_cameras_start_at_the_reference_view() -> None:
    cams = check_cameras(ConversionConfig(ring_views=3, elevations=(10.0, -10.0)))
    assert len(cams) == 7
    assert float(cams.elevation[0]) == 0.0 and float(cams.azimuth[0]) == 0.0


def test_an_empty_nerf_is_a_clear_error(cache_dir: Path) -> None:
    with pytest.raises(EmptySurfaceError, match="the NeRF is empty"):
        convert(_dmtet(cache_dir), VaseField(body_density=0.0, neck_density=0.0), FAST)


def test_config_validation() -> None:
    for bad in ({"levels": ()}, {"levels": (0.0,)}, {"levels": (1.0,)}, {"ring_views": 0}, {"resolution": 4}):
        with pytest.raises(ValueError):
            ConversionConfig(**bad)
