"""Volume rendering of a radiance field: stratified samples in the box, occupancy-grid skipping,
per-ray compositing in log space.

Compositing works with optical depths τ_i = σ_i·δ_i: transmittance T_i = exp(−Σ_{j<i} τ_j),
alpha_i = −expm1(−τ_i), weight w_i = T_i·alpha_i, and opacity = −expm1(−Σ τ). Summing in log
space keeps T in [0, 1] for any density (no product of thousands of factors), and the
opacity formula is exact even when Σ w rounds above 1. Densities are clamped below
``max_density`` so τ stays finite (inf·0 would give NaN for zero-length steps).

The occupancy grid keeps a decayed running maximum of density per cell, refreshed every
``update_every`` steps; samples in cells below the threshold are not evaluated at all (their
density is taken as 0), which is where most of the field's cost goes on an object that fills
a fraction of its box.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor, nn

from morpheus_core.cameras import Cameras
from morpheus_core.geometry.nerf import RadianceField
from morpheus_core.render.output import RenderOutput
from morpheus_core.render.sample_budget import FieldValues, SampleBudget, field_values
from morpheus_core.runtime.devices import filled_like, to_device


@dataclass(frozen=True)
class VolumeRenderConfig:
    """How a radiance field is volume-rendered: samples per ray, normals, memory and sample skipping."""

    n_samples: int = 256
    """Samples per ray, evenly spaced across the ray's span of the box (the paper: 256)."""
    stratified: bool = True
    """Jitter each sample within its bin (else bin centres); the NeRF stage jitters training renders only."""
    with_normals: bool = True
    """Render normals too (6 density queries a sample); the NeRF stage asks when normal_smooth_weight > 0."""
    max_density: float = 1e10
    """Densities are clamped below this so optical depth stays finite (inf·0 is NaN for zero-length steps)."""
    chunk_points: int = 1 << 18
    """Points per field call: bounds the field's peak memory, not the result."""
    chunk_rays: int = 1 << 14
    """Rays per pass of a render without gradients (previews, evaluation, the NeRF→DMTet conversion):
    bounds its per-sample buffers, which for many views at once ran a GPU out of memory, not the
    result. Training renders take one pass: their backward needs every sample."""
    # Why these defaults (H200): normals were 6/7 of a NeRF step's encoder work, so they are skipped
    # where they barely count; the transmittance probe cost as much as it saved (paper NeRF step 177
    # vs 161 ms at one object, equal at eight; blob-shaped field), so it is off.
    normal_weight_threshold: float = 1e-4
    """Normals only where a sample's compositing weight (its share of the normal) exceeds this; 0: everywhere."""
    transmittance_threshold: float = 0.0
    """> 0: training renders evaluate only samples whose transmittance (no-grad density probe) exceeds it; 0: off."""
    # Measured (H200, paper NeRF, one device call each): eager, padded 94–95 vs exact 86–99 ms a step
    # at one object, 319–345 vs 290–301 ms at four. Graphed vs exact: 90–99 vs 109–133 ms alone, but
    # 870 vs 796 ms and 103 vs 65 GiB at eight, and out of memory at sixteen. A batch keeps the GPU
    # busy, so the padding's extra field work and the graphs' held activations cost more than the
    # host time they save; alone, the host is what a step waits for.
    sample_buffer: Literal["auto", "exact", "padded", "graphed"] = "auto"
    """How training renders gather and evaluate the samples: ``exact`` (the kept ones; one host sync
    per gather), ``padded`` (a fixed-size buffer sized by ``SampleBudget``: no sync, shapes that stay
    put), ``graphed`` (padded, and the field's forward and backward on each buffer replayed from a
    CUDA graph: CUDA only); ``auto``: graphed for an object optimised alone on CUDA, else exact."""

    def sample_buffer_on(self, device: torch.device, alone: bool = True) -> str:
        """``sample_buffer`` with ``auto`` resolved for ``device`` and whether the object is optimised
        ``alone`` (not in a batch); ``graphed`` off CUDA raises."""
        if self.sample_buffer == "auto":
            return "graphed" if device.type == "cuda" and alone else "exact"
        if self.sample_buffer == "graphed" and device.type != "cuda":
            raise ValueError(f"sample_buffer='graphed' needs a CUDA device, got {device}; use auto, exact or padded")
        return self.sample_buffer

    def __post_init__(self) -> None:
        if self.n_samples < 1 or self.chunk_points < 1 or self.chunk_rays < 1:
            raise ValueError("n_samples, chunk_points and chunk_rays must be ≥ 1")
        if self.max_density <= 0:
            raise ValueError("max_density must be positive")
        if self.sample_buffer not in ("auto", "exact", "padded", "graphed"):
            raise ValueError(f"sample_buffer must be auto, exact, padded or graphed, got {self.sample_buffer!r}")
        for name in ("normal_weight_threshold", "transmittance_threshold"):
            if not 0.0 <= getattr(self, name) < 1.0:
                raise ValueError(f"{name} must be in [0, 1), got {getattr(self, name)}")


@dataclass(frozen=True)
class OccupancyGridConfig:
    """A decayed running maximum of density per cell: samples in empty cells are not evaluated."""

    resolution: int = 64
    """Cells per side of the occupancy grid over the field's [−r, r]³ box."""
    decay: float = 0.95
    """Each refresh keeps max(decay · old, new) per cell (0–1): cells the field empties fade out."""
    density_threshold: float = 0.01
    """Cells with density below this are skipped: at δ ≈ 0.0135 (256 samples/box) alpha ≈ 1e-4, invisible."""
    update_every: int = 16
    """Steps between refreshes (one jittered density probe per cell each)."""

    def __post_init__(self) -> None:
        if self.resolution < 1 or self.update_every < 1:
            raise ValueError("resolution and update_every must be ≥ 1")
        if not 0.0 <= self.decay <= 1.0:
            raise ValueError(f"decay must be in [0, 1], got {self.decay}")


class OccupancyGrid(nn.Module):
    """A decayed max of density per cell of the [−r, r]³ box. Until the first refresh every cell
    counts as occupied, so a fresh grid never hides anything."""

    def __init__(self, config: OccupancyGridConfig, bbox_radius: float) -> None:
        super().__init__()
        self.config = config
        self.bbox_radius = bbox_radius
        n = config.resolution
        self.register_buffer("density", torch.full((n, n, n), float("inf")))

    def cell_index(self, points: Tensor) -> Tensor:
        n = self.config.resolution
        cell = torch.floor((points / self.bbox_radius + 1) * 0.5 * n).long().clamp_(0, n - 1)
        return (cell[..., 0] * n + cell[..., 1]) * n + cell[..., 2]

    def occupied(self, points: Tensor) -> Tensor:
        return self.density.reshape(-1)[self.cell_index(points)] > self.config.density_threshold

    @property
    def occupied_fraction(self) -> float:
        return float((self.density > self.config.density_threshold).float().mean())

    @torch.no_grad()
    def refresh(self, field: RadianceField, generator: torch.Generator | None = None) -> None:
        """One jittered density probe per cell; keep max(decay·old, new)."""
        n = self.config.resolution
        device = self.density.device
        axis = torch.arange(n, device=device, dtype=torch.float32)
        cells = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
        jitter = to_device(torch.rand(cells.shape, generator=generator, dtype=torch.float32), device)
        points = ((cells + jitter) / n * 2 - 1) * self.bbox_radius
        fresh = torch.cat([field.density(c).float() for c in points.split(1 << 18)]).reshape(n, n, n)
        fresh = torch.nan_to_num(fresh, nan=0.0, posinf=torch.finfo(fresh.dtype).max)
        old = torch.where(torch.isinf(self.density), torch.zeros_like(self.density), self.density)
        self.density.copy_(torch.maximum(old * self.config.decay, fresh))

    def maybe_refresh(self, field: RadianceField, step: int, generator: torch.Generator | None = None) -> bool:
        if step % self.config.update_every:
            return False
        self.refresh(field, generator)
        return True


def ray_box(origins: Tensor, dirs: Tensor, radius: float) -> tuple[Tensor, Tensor, Tensor]:
    """Slab test against [−r, r]³: entry and exit distances (clamped at 0) and a hit mask."""
    safe = torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
    t0 = (-radius - origins) / safe
    t1 = (radius - origins) / safe
    near = torch.minimum(t0, t1).amax(-1).clamp_min(0.0)
    far = torch.maximum(t0, t1).amin(-1)
    hit = far > near
    return near, torch.where(hit, far, near), hit


def _query(
    field: RadianceField, points: Tensor, keep: Tensor, with_normals: bool, chunk: int, density_only: bool = False
) -> tuple[Tensor, Tensor, Tensor | None]:
    """Evaluate the field only at ``keep`` points (in chunks); zeros elsewhere."""
    index = keep.nonzero().squeeze(-1)
    if index.numel() == 0:
        n = points.shape[0]
        return points.new_zeros(n), points.new_zeros(n, 3), points.new_zeros(n, 3) if with_normals else None
    if density_only:
        n = points.shape[0]
        values = torch.cat([field.density(points[i]).to(points.dtype) for i in index.split(chunk)])
        return points.new_zeros(n).index_put((index,), values), points.new_zeros(n, 3), None
    return _query_at(points, index, lambda x: field_values(field, x, with_normals, chunk), with_normals)


def _query_at(
    points: Tensor, index: Tensor, evaluate: FieldValues, with_normals: bool, padded: bool = False
) -> tuple[Tensor, Tensor, Tensor | None]:
    """The field (``evaluate``) at the points ``index`` names, zeros elsewhere. ``padded``: entries
    equal to ``len(points)`` are padding slots (``SampleBudget.gather``); slot i evaluates point i
    and its result lands in a slot that is cut off. Padding on one shared point would send every
    padding gradient to the same hash-table cells, and those contended atomics made the backward
    3.5× slower (H200)."""
    n = points.shape[0]
    source = torch.where(index < n, index, torch.arange(index.shape[0], device=index.device) % n) if padded else index
    # One contiguous buffer per quantity: the compositing reads them whole, not as strided views.
    placed = [points.new_zeros((n + 1, *v.shape[1:])).index_put((index,), v)[:n] for v in evaluate(points[source])]
    return placed[0], placed[1], placed[2] if with_normals else None


@torch.no_grad()
def _visible(field: RadianceField, points: Tensor, keep: Tensor, step: Tensor, config: VolumeRenderConfig) -> Tensor:
    """``keep`` (R, S) without the samples whose transmittance is already below the threshold."""
    density, _, _ = _query(field, points, keep.reshape(-1), False, config.chunk_points, density_only=True)
    tau = torch.nan_to_num(density, nan=0.0).clamp(0.0, config.max_density).reshape(keep.shape) * step
    before = torch.cumsum(tau, -1) - tau
    return keep & (before < -math.log(config.transmittance_threshold))


def _background(background: Tensor | float | tuple[float, float, float], like: Tensor, batch: int) -> Tensor:
    bg = filled_like(background, like)
    if bg.dim() == 0:
        bg = bg.expand(3)
    return bg.expand(batch, 3) if bg.dim() == 1 else bg


Query = Callable[[Tensor, bool, str], tuple[Tensor, Tensor, Tensor | None]]
"""(keep (R, S), with normals, buffer name) → density, albedo, normals at the kept samples, zeros elsewhere."""


def _bins(n_rays: int, s: int, like: Tensor, config: VolumeRenderConfig, generator: torch.Generator | None) -> Tensor:
    """(R, S) sample positions in bin units along each ray: jittered within the bins, or their centres."""
    u = torch.arange(s, dtype=like.dtype, device=like.device)
    if not config.stratified:
        return (u + 0.5).expand(n_rays, s)
    # Drawn by the CPU generator as always: drawing it on the GPU from a seed of that generator
    # (no 16 MB copy) shifted the results systematically — reference PSNR up, novel-view PSNR
    # down, on the GPU (24 pairs) and emulated on the CPU (8 pairs): benchmarks/results/quality_nosync_h200.md.
    return u + to_device(torch.rand((n_rays, s), generator=generator, dtype=like.dtype), like.device)


def _samples(o: Tensor, d: Tensor, near: Tensor, far: Tensor, u: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    step = ((far - near) / u.shape[1]).unsqueeze(-1)  # δ per ray: the bin width
    t = near.unsqueeze(-1) + u * step  # (R, S)
    return t, step, o.unsqueeze(1) + t.unsqueeze(-1) * d.unsqueeze(1)


def _composite(query: Query, keep: Tensor, t: Tensor, step: Tensor, bg: Tensor, config: VolumeRenderConfig,
               key: str) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Per-ray rgb on ``bg``, opacity, depth and normal (R, ·) from the field at the ``keep`` samples."""
    s = t.shape[1]
    density, albedo, _ = query(keep, False, key)
    density = torch.nan_to_num(density, nan=0.0).clamp(0.0, config.max_density).reshape(-1, s)
    tau = density * step
    cum = torch.cumsum(tau, -1)
    log_t = torch.cat((torch.zeros_like(cum[:, :1]), -cum[:, :-1]), -1)
    weights = torch.exp(log_t) * -torch.expm1(-tau)  # (R, S)
    opacity = -torch.expm1(-cum[:, -1:])
    rgb = (weights.unsqueeze(-1) * albedo.reshape(-1, s, 3)).sum(1) + (1 - opacity) * bg
    depth = (weights * t).sum(-1, keepdim=True)
    if not config.with_normals:
        return rgb, opacity, depth, torch.zeros_like(rgb)
    visible = keep & (weights.detach() > config.normal_weight_threshold)
    _, _, normal = query(visible, True, f"{key}/normals")
    return rgb, opacity, depth, (weights.unsqueeze(-1) * normal.reshape(-1, s, 3)).sum(1)  # type: ignore[union-attr]


def _images(values: tuple[Tensor, ...], batch: int, height: int, width: int) -> RenderOutput:
    return RenderOutput(*(x.reshape(batch, height, width, -1) for x in values))


def render_volume(
    field: RadianceField,
    cameras: Cameras,
    height: int,
    width: int,
    config: VolumeRenderConfig | None = None,
    background: Tensor | float | tuple[float, float, float] = 1.0,
    occupancy: OccupancyGrid | None = None,
    generator: torch.Generator | None = None,
    budget: SampleBudget | None = None,
    budget_key: str = "render",
) -> RenderOutput:
    """Render ``field`` from every camera: rgb on ``background``, opacity, depth, normal. With a
    ``budget``, the field is evaluated on its padded buffers ``budget_key`` (and ``…/normals``)."""
    config = config or VolumeRenderConfig()

    def render_rays(o: Tensor, d: Tensor, u: Tensor, bg: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        near, far, hit = ray_box(o, d, field.bbox_radius)
        t, step, points = _samples(o, d, near, far, u)
        keep = hit.unsqueeze(-1).expand(-1, config.n_samples)
        if occupancy is not None:
            keep = keep & occupancy.occupied(points)
        flat = points.reshape(-1, 3)
        if config.transmittance_threshold > 0 and torch.is_grad_enabled():
            keep = _visible(field, flat, keep, step, config)

        def query(keep: Tensor, normals: bool, key: str) -> tuple[Tensor, Tensor, Tensor | None]:
            if budget is None:
                return _query(field, flat, keep.reshape(-1), normals, config.chunk_points)
            index, _ = budget.gather(key, keep)
            return _query_at(flat, index, budget.evaluator(key, field, normals, config.chunk_points), normals,
                             padded=True)

        return _composite(query, keep, t, step, bg, config, budget_key)

    origins, dirs = cameras.rays(height, width)
    o, d = origins.reshape(-1, 3), dirs.reshape(-1, 3)
    u = _bins(o.shape[0], config.n_samples, o, config, generator)  # all rays' jitter in one draw, chunked or not
    bg = _background(background, o, len(cameras)).repeat_interleave(height * width, 0)
    n, chunk = o.shape[0], config.chunk_rays
    if torch.is_grad_enabled() or budget is not None or n <= chunk:
        values = render_rays(o, d, u, bg)
    else:
        parts = [render_rays(o[i:i + chunk], d[i:i + chunk], u[i:i + chunk], bg[i:i + chunk])
                 for i in range(0, n, chunk)]
        values = tuple(torch.cat(x) for x in zip(*parts, strict=True))
    return _images(values, len(cameras), height, width)


@torch.no_grad()
def render_silhouette(
    field: RadianceField,
    cameras: Cameras,
    height: int,
    width: int,
    n_samples: int = 128,
    occupancy: OccupancyGrid | None = None,
    level: float = 0.5,
    segment: int = 16,
) -> Tensor:
    """(B, H, W) bool: where ``render_volume``'s opacity (unstratified, same samples and density
    clamp) exceeds ``level``. Only densities are queried, ``segment`` samples per ray at a time,
    and a ray stops once its optical depth passes −log(1 − level): the rest of it cannot change
    the answer, and behind an opaque surface is where most samples of a solid object lie."""
    if not 0.0 < level < 1.0 or n_samples < 1 or segment < 1:
        raise ValueError("level must lie in (0, 1), n_samples and segment must be ≥ 1")
    origins, dirs = cameras.rays(height, width)
    o, d = origins.reshape(-1, 3), dirs.reshape(-1, 3)
    near, far, hit = ray_box(o, d, field.bbox_radius)
    step = (far - near) / n_samples
    depth_needed = -math.log1p(-level)
    tau = torch.zeros_like(near)
    live = hit.nonzero().squeeze(-1)
    for start in range(0, n_samples, segment):
        if live.numel() == 0:
            break
        u = torch.arange(start, min(start + segment, n_samples), dtype=o.dtype, device=o.device) + 0.5
        t = near[live, None] + u * step[live, None]  # (R, s)
        points = (o[live, None] + t.unsqueeze(-1) * d[live, None]).reshape(-1, 3)
        keep = torch.ones(points.shape[0], dtype=torch.bool, device=o.device) if occupancy is None else \
            occupancy.occupied(points)
        sigma = points.new_zeros(points.shape[0])
        index = keep.nonzero().squeeze(-1)
        if index.numel():
            sigma[index] = torch.cat([field.density(points[i]).to(o.dtype) for i in index.split(1 << 18)])
        sigma = torch.nan_to_num(sigma, nan=0.0).clamp(0.0, 1e10).reshape(t.shape)
        tau[live] += (sigma * step[live, None]).sum(-1)
        live = live[tau[live] <= depth_needed]
    return (tau > depth_needed).reshape(len(cameras), height, width)
