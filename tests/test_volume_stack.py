"""Several objects' fields rendered together (``render_volume_stack``, ``FieldStack``,
``encode_stacked``): each object's render and gradients equal its own ``render_volume``'s."""

from __future__ import annotations

import secrets

import pytest
import torch

from morpheus_core.cameras import sample_orbit
from morpheus_core.geometry.hashgrid import HashGrid, HashGridConfig, encode_stacked
from morpheus_core.geometry.nerf import NerfConfig, NerfField
from morpheus_core.geometry.nerf_stack import FieldStack
from morpheus_core.render.volume import OccupancyGrid, OccupancyGridConfig, VolumeRenderConfig, render_volume
from morpheus_core.render.volume_stack import render_volume_stack

GRID = HashGridConfig(n_levels=4, log2_table_size=10, base_resolution=4, per_level_scale=1.8)


def _fields(seed: int, k: int, device: torch.device) -> list[NerfField]:
    return [NerfField(NerfConfig(grid=GRID, hidden=16), generator=torch.Generator().manual_seed(seed + i)).to(device)
            for i in range(k)]


def _grads(fields: list[NerfField]) -> list[torch.Tensor]:
    return [p.grad.clone() for f in fields for p in f.parameters()]


@pytest.mark.parametrize(("seed", "chunk"), [(0, 1 << 18), (secrets.randbits(31), 1 << 18), (1, 41)])
def test_stacked_renders_and_gradients_equal_each_objects_own_render(seed: int, chunk: int,
                                                                     device: torch.device) -> None:
    """Chunks of 41 points per object (123 per stacked query) span objects and split them."""
    fields = _fields(seed % 1000, 3, device)
    grids = []
    for i, f in enumerate(fields):
        grid = OccupancyGrid(OccupancyGridConfig(resolution=16, density_threshold=1e-3), f.bbox_radius).to(device)
        grid.refresh(f, torch.Generator().manual_seed(seed + 10 + i))
        grids.append(grid)
    # Object 1 sees two views: objects need not have the same number of rays.
    cams = [sample_orbit(n, generator=torch.Generator().manual_seed(seed + 20 + i)).to(device)
            for i, n in enumerate((1, 2, 1))]
    config = VolumeRenderConfig(n_samples=40, with_normals=True, chunk_points=chunk)
    targets = [torch.rand(len(c), 12, 12, 3, generator=torch.Generator().manual_seed(seed + 30 + i)).to(device)
               for i, c in enumerate(cams)]

    def loss(outs: list) -> torch.Tensor:
        return sum(((o.rgb - t) ** 2).mean() + o.normal.square().mean() + o.depth.mean()
                   for o, t in zip(outs, targets, strict=True))

    alone = [render_volume(f, c, 12, 12, config, 1.0, g, torch.Generator().manual_seed(seed + 40 + i))
             for i, (f, c, g) in enumerate(zip(fields, cams, grids, strict=True))]
    loss(alone).backward()
    alone_grads = _grads(fields)
    for f in fields:
        f.zero_grad()
    together = render_volume_stack(FieldStack(fields), cams, 12, 12, config, 1.0, grids,
                                   [torch.Generator().manual_seed(seed + 40 + i) for i in range(3)])
    loss(together).backward()
    for a, b in zip(together, alone, strict=True):
        for name in ("rgb", "opacity", "depth", "normal"):
            torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=1e-5, atol=1e-6)
    for a, b in zip(_grads(fields), alone_grads, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-7)
    assert not torch.equal(alone[0].rgb, alone[2].rgb)  # the objects really differ
    assert all(g.abs().sum() > 0 for g in alone_grads)


def test_stacked_encode_equals_each_grids_forward_and_gradients() -> None:
    g = torch.Generator().manual_seed(secrets.randbits(31))
    grids = [HashGrid(GRID, generator=g) for _ in range(3)]
    counts = [5, 0, 7]  # an object with no points in this call
    obj = torch.repeat_interleave(torch.arange(3), torch.tensor(counts))
    x = torch.rand(sum(counts), 3, generator=g, dtype=torch.float64, requires_grad=True)
    for grid in grids:
        grid.table.data = grid.table.data.double()
    out = encode_stacked(grids, x, obj)
    weights = torch.randn(out.shape, generator=g, dtype=torch.float64)
    (out * weights).sum().backward()
    stacked = [x.grad.clone()] + [grid.table.grad.clone() for grid in grids]
    x.grad = None
    for grid in grids:
        grid.table.grad = None
    parts = [grids[i](xi) for i, xi in enumerate(x.split(counts))]
    torch.testing.assert_close(out, torch.cat(parts), rtol=0, atol=0)
    (torch.cat(parts) * weights).sum().backward()
    own = [x.grad] + [grid.table.grad if grid.table.grad is not None else torch.zeros_like(grid.table)
                      for grid in grids]
    for a, b in zip(stacked, own, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-15)
    assert stacked[2].abs().sum() == 0 and stacked[1].abs().sum() > 0  # grid 1 had no points


def test_stacking_refuses_objects_that_do_not_fit_together() -> None:
    g = torch.Generator().manual_seed(secrets.randbits(31))
    a, b = HashGrid(GRID, generator=g), HashGrid(GRID, generator=g)
    x, obj = torch.rand(4, 3, generator=g), torch.tensor([0, 0, 1, 1])
    with pytest.raises(ValueError, match="one config"):
        encode_stacked([a, HashGrid(HashGridConfig(n_levels=3, log2_table_size=10), generator=g)], x, obj)
    with pytest.raises(ValueError, match="one object index per point"):
        encode_stacked([a, b], x, obj[:3])
    b.set_active_levels(2)
    with pytest.raises(ValueError, match="same active levels"):
        encode_stacked([a, b], x, obj)
    fields = _fields(0, 2, torch.device("cpu"))
    stack = FieldStack(fields)
    with pytest.raises(ValueError, match="counts"):
        stack.query(x, obj, [3, 3])
    with pytest.raises(ValueError, match="one NerfConfig"):
        FieldStack([fields[0], NerfField(NerfConfig(grid=GRID, hidden=8))])
    cams = [sample_orbit(1, generator=g) for _ in range(2)]
    with pytest.raises(ValueError, match="one camera batch"):
        render_volume_stack(stack, cams[:1], 8, 8, VolumeRenderConfig(n_samples=8))
    with pytest.raises(ValueError, match="transmittance"):
        render_volume_stack(stack, cams, 8, 8, VolumeRenderConfig(n_samples=8, transmittance_threshold=0.1))

