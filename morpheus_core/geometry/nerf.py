"""The NeRF field of stage 1a: hash-grid encoding, a density MLP with a centred blob, an albedo head.

Density is ``trunc_exp(raw + blob)``: exp in the forward pass, but the backward clamps the
exponent so one large raw value cannot blow the gradient up. The blob bias (Magic3D's
``scale·(1 − |x|/std)``) starts the optimisation from a soft ball at the centre instead of
empty space, which SDS alone cannot escape. Normals are minus the density gradient by central
differences (six extra density queries), normalised safely.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import torch
from torch import Tensor, nn

from morpheus_core.geometry.field_heads import evaluate_heads
from morpheus_core.geometry.hashgrid import HashGrid, HashGridConfig
from morpheus_core.vectors import safe_normalize

# exp(15) ≈ 3.3e6: the largest factor trunc_exp lets into a gradient.
_TRUNC_EXP_MAX = 15.0
# exp(88) overflows float32; densities beyond ~1e30 change nothing in the compositing anyway.
_DENSITY_MAX_LOG = 69.0


class _TruncExp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: Tensor) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(x)
        return torch.exp(x.clamp(max=_DENSITY_MAX_LOG))

    @staticmethod
    def backward(ctx, grad: Tensor) -> Tensor:  # type: ignore[override]
        (x,) = ctx.saved_tensors
        return grad * torch.exp(x.clamp(max=_TRUNC_EXP_MAX))


def trunc_exp(x: Tensor) -> Tensor:
    """exp(x) with the backward's exponent clamped at 15 (and the forward's at 69, finite in fp32)."""
    return _TruncExp.apply(x)


@dataclass
class FieldSample:
    """What a radiance field returns for N points: density (N,), albedo (N, 3), normal (N, 3) or None."""

    density: Tensor
    albedo: Tensor
    normal: Tensor | None = None


class RadianceField(Protocol):
    """Anything the volume renderer can render: the NeRF below, or an analytic field in tests."""

    bbox_radius: float

    def density(self, points: Tensor) -> Tensor: ...

    def query(self, points: Tensor, with_normals: bool) -> FieldSample: ...


def central_difference_normals(density_fn: object, points: Tensor, eps: float) -> Tensor:
    """−∇σ / |∇σ| from six density queries; points in empty, flat regions get a zero normal."""
    offsets = torch.eye(3, dtype=points.dtype, device=points.device) * eps
    probes = torch.cat((points.unsqueeze(1) + offsets, points.unsqueeze(1) - offsets), 1)  # (N, 6, 3)
    sigma = density_fn(probes.reshape(-1, 3)).reshape(-1, 2, 3)  # type: ignore[operator]
    grad = (sigma[:, 0] - sigma[:, 1]) / (2 * eps)
    return safe_normalize(-grad)


def head_mlp(n_in: int, hidden: int, n_hidden_layers: int, n_out: int) -> nn.Sequential:
    """A field head: ``n_hidden_layers`` × (Linear to ``hidden``, ReLU), then a Linear to ``n_out``."""
    layers: list[nn.Module] = []
    width = n_in
    for _ in range(n_hidden_layers):
        layers += [nn.Linear(width, hidden), nn.ReLU(inplace=True)]
        width = hidden
    layers.append(nn.Linear(width, n_out))
    return nn.Sequential(*layers)


def _seeded_linear_init(layers: tuple[nn.Module, ...], generator: torch.Generator) -> None:
    """PyTorch's default Linear init, U(±1/√fan_in), drawn from ``generator`` for reproducibility."""
    with torch.no_grad():
        for layer in layers:
            if isinstance(layer, nn.Linear):
                bound = layer.in_features**-0.5
                layer.weight.uniform_(-bound, bound, generator=generator)
                layer.bias.uniform_(-bound, bound, generator=generator)


@dataclass(frozen=True)
class NerfConfig:
    """The paper's field: 16×2 hash grid (progressive), MLPs of 64 × 2 hidden layers."""

    grid: HashGridConfig = field(
        default_factory=lambda: HashGridConfig(start_levels=8, start_step=2000, update_steps=500)
    )
    """The field's hash-grid encoding: the paper's, 8 of 16 levels at first, one more every 500 steps from 2k."""
    hidden: int = 64
    """Width of the density and albedo MLPs' hidden layers (the paper: 64)."""
    n_hidden_layers: int = 2
    """Hidden layers of the density and albedo MLPs each (the paper: 2)."""
    bbox_radius: float = 1.0
    """Half side r of the field's [−r, r]³ box (world units); rays are clipped to it and the grid spans it."""
    blob_density: float = 10.0
    """Log-density bias at the centre of the initial blob, scale·(1 − |x|/radius) (Magic3D): SDS starts from a ball."""
    blob_radius: float = 0.5
    """Radius (world units) where the blob bias falls to 0; it is negative (emptier) further out."""
    normal_eps: float = 0.01
    """Step (world units) of the central differences whose density gradient gives the normals."""

    def __post_init__(self) -> None:
        if self.bbox_radius <= 0 or self.blob_radius <= 0 or self.normal_eps <= 0:
            raise ValueError("bbox_radius, blob_radius and normal_eps must be positive")


class NerfField(nn.Module):
    """Density and albedo at world points inside the [−r, r]³ box."""

    def __init__(self, config: NerfConfig | None = None, generator: torch.Generator | None = None) -> None:
        super().__init__()
        self.config = config or NerfConfig()
        self.bbox_radius = self.config.bbox_radius
        self.encoding = HashGrid(self.config.grid, generator=generator)
        dim = self.encoding.output_dim
        self.density_mlp = head_mlp(dim, self.config.hidden, self.config.n_hidden_layers, 1)
        self.albedo_mlp = head_mlp(dim, self.config.hidden, self.config.n_hidden_layers, 3)
        if generator is not None:
            _seeded_linear_init((*self.density_mlp, *self.albedo_mlp), generator)

    def _features(self, points: Tensor) -> Tensor:
        return self.encoding((points / self.bbox_radius + 1) * 0.5)

    def _blob(self, points: Tensor) -> Tensor:
        cfg = self.config
        radius = torch.sqrt((points * points).sum(-1) + 1e-12)
        return cfg.blob_density * (1 - radius / cfg.blob_radius)

    def density(self, points: Tensor) -> Tensor:
        raw, _ = evaluate_heads(self._features(points), self.density_mlp, None)
        return trunc_exp(raw.squeeze(-1).float() + self._blob(points).float())

    def query(self, points: Tensor, with_normals: bool = False) -> FieldSample:
        raw, raw_albedo = evaluate_heads(self._features(points), self.density_mlp, self.albedo_mlp)
        density = trunc_exp(raw.squeeze(-1).float() + self._blob(points).float())
        albedo = torch.sigmoid(raw_albedo.float())  # type: ignore[union-attr]
        normal = central_difference_normals(self.density, points, self.config.normal_eps) if with_normals else None
        return FieldSample(density, albedo, normal)

    def update_step(self, step: int) -> None:
        self.encoding.update_step(step)
