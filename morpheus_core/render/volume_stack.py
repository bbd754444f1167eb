"""All objects of a batch volume-rendered together: their samples go through one stacked field
query (``FieldStack``), so the per-sample work is one launch per kernel for the whole batch instead
of one per object. Each object's renders equal its own ``render_volume`` (exact sample buffers)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from morpheus_core.cameras import Cameras
from morpheus_core.geometry.nerf_stack import FieldStack
from morpheus_core.render.output import RenderOutput
from morpheus_core.render.volume import (
    OccupancyGrid,
    VolumeRenderConfig,
    _background,
    _bins,
    _composite,
    _images,
    _query_at,
    _samples,
    ray_box,
)


def render_volume_stack(
    stack: FieldStack,
    cameras: Sequence[Cameras],
    height: int,
    width: int,
    config: VolumeRenderConfig,
    background: float = 1.0,
    occupancy: Sequence[OccupancyGrid] | None = None,
    generators: Sequence[torch.Generator] | None = None,
) -> list[RenderOutput]:
    """``render_volume`` of each object of ``stack`` from its own cameras (``occupancy`` and
    ``generators``: one per object, each drawing its object's jitter as ``render_volume`` would),
    with every object's kept samples evaluated by stacked field queries of ``config.chunk_points``
    points per object in the stack (exact buffers: one host read per query for the counts).

    Why the chunk grows with the stack (H200, paper NeRF at 8 objects): chunks of 2^18 points gave
    back the one-by-one step time (957 ms a step); one query of every sample took 696 ms, but at
    87 GiB against 63, and 16 objects ran out of memory."""
    k = len(stack)
    if len(cameras) != k or any(len(x) != k for x in (occupancy or [None] * k, generators or [None] * k)):
        raise ValueError(f"one camera batch, occupancy grid and generator per object ({k} objects)")
    if config.transmittance_threshold > 0:
        raise ValueError("render_volume_stack has no transmittance probe: use render_volume per object")
    s = config.n_samples
    chunk = config.chunk_points * k
    rays = [c.rays(height, width) for c in cameras]
    o = torch.cat([r[0].reshape(-1, 3) for r in rays])
    d = torch.cat([r[1].reshape(-1, 3) for r in rays])
    n_rays = [len(c) * height * width for c in cameras]
    near, far, hit = ray_box(o, d, stack.bbox_radius)
    gens = generators or [None] * k
    u = torch.cat([_bins(n, s, o, config, g) for n, g in zip(n_rays, gens, strict=True)])
    t, step, points = _samples(o, d, near, far, u)
    ray_obj = torch.cat([torch.full((n,), i, dtype=torch.int64, device=o.device) for i, n in enumerate(n_rays)])
    keep = hit.unsqueeze(-1).expand(-1, s)
    if occupancy is not None:
        keep = keep & _occupied_stack(occupancy, points, ray_obj)
    flat = points.reshape(-1, 3)

    def query(keep: Tensor, normals: bool, _key: str) -> tuple[Tensor, Tensor, Tensor | None]:
        per_object = torch.zeros(k, dtype=torch.int64, device=o.device).index_add_(0, ray_obj, keep.sum(1))
        counts = per_object.tolist()
        index = keep.reshape(-1).nonzero().squeeze(-1)
        obj = ray_obj[index // s]
        return _query_at(flat, index, lambda x: _stack_values(stack, x, obj, counts, normals, chunk),
                         normals)

    bg = torch.cat([_background(background, o, len(c)).repeat_interleave(height * width, 0) for c in cameras])
    values = _composite(query, keep, t, step, bg, config, "stack")
    per_object = [v.split(n_rays) for v in values]
    return [_images(tuple(v[i] for v in per_object), len(c), height, width) for i, c in enumerate(cameras)]


def _stack_values(stack: FieldStack, points: Tensor, obj: Tensor, counts: list[int], with_normals: bool,
                  chunk: int) -> tuple[Tensor, ...]:
    """``field_values`` of a stack: density, albedo (and normals) at ``points`` sorted by object
    (``counts`` per object), ``chunk`` points per stacked query (a chunk may span objects)."""
    ends = torch.tensor(counts).cumsum(0).tolist()
    starts = [e - c for e, c in zip(ends, counts, strict=True)]
    values: list[list[Tensor]] = []
    for lo in range(0, max(len(points), 1), chunk):
        hi = min(lo + chunk, len(points))
        part = [max(0, min(hi, e) - max(lo, b)) for b, e in zip(starts, ends, strict=True)]
        sample = stack.query(points[lo:hi], obj[lo:hi], part, with_normals)
        values.append([sample.density, sample.albedo] + ([sample.normal] if with_normals else []))  # type: ignore[list-item]
    return tuple(torch.cat(v).to(points.dtype) for v in zip(*values, strict=True))


def _occupied_stack(grids: Sequence[OccupancyGrid], points: Tensor, ray_obj: Tensor) -> Tensor:
    """(R, S): ``grids[object of the ray].occupied`` at every sample, in one gather."""
    first = grids[0]
    if any(g.config != first.config or g.bbox_radius != first.bbox_radius for g in grids):
        raise ValueError("stacked occupancy grids must share their config and box")
    cells = first.cell_index(points) + (ray_obj * first.config.resolution**3).unsqueeze(-1)
    return torch.stack([g.density.reshape(-1) for g in grids]).reshape(-1)[cells] > first.config.density_threshold
