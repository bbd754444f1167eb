"""Texture field: the albedo of an optimised mesh, as a hash grid and a small MLP over the object box.

* ``TextureField``: a hash grid over the object box [-r, r]^3 (mapped to [0, 1]^3) and a small MLP
  with a sigmoid, so albedo stays in (0, 1). The mesh renderer queries it at surface points.
* Baking it into a UV texture is ``morpheus_core.export.uv_bake``; writing the textured GLB / OBJ
  is ``morpheus_core.export.gltf``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from morpheus_core.geometry.hashgrid import HashGrid, HashGridConfig


@dataclass(frozen=True)
class TextureFieldConfig:
    """The albedo field of the mesh stages: a hash grid over the object box and a small MLP."""

    hashgrid: HashGridConfig = field(default_factory=HashGridConfig)
    bound: float = 1.0
    """Half side r (world units) of the [−r, r]³ box the field covers; points outside are clamped to it."""
    hidden_dim: int = 64
    """Width of the MLP's hidden layers."""
    hidden_layers: int = 1
    """Hidden layers of the MLP (0: a linear map from the hash-grid features)."""

    def __post_init__(self) -> None:
        if not self.bound > 0:
            raise ValueError(f"bound must be positive, got {self.bound}")
        if self.hidden_dim < 1 or self.hidden_layers < 0:
            raise ValueError("hidden_dim must be ≥ 1 and hidden_layers ≥ 0")


class TextureField(nn.Module):
    """Albedo in (0, 1) at world points (..., 3): sigmoid(MLP(hash grid((p + r) / 2r)))."""

    def __init__(self, config: TextureFieldConfig | None = None, generator: torch.Generator | None = None) -> None:
        super().__init__()
        self.config = config or TextureFieldConfig()
        self.encoding = HashGrid(self.config.hashgrid, generator=generator)
        width, layers = self.encoding.output_dim, []
        for _ in range(self.config.hidden_layers):
            layers += [nn.Linear(width, self.config.hidden_dim), nn.ReLU()]
            width = self.config.hidden_dim
        layers.append(nn.Linear(width, 3))
        self.mlp = nn.Sequential(*layers)
        if generator is not None:  # reproducible MLP initialisation as well as table
            with torch.no_grad():
                for p in self.mlp.parameters():
                    bound = 1.0 / math.sqrt(p.shape[-1])
                    p.copy_((torch.rand(p.shape, generator=generator) * 2 - 1) * bound)

    def forward(self, points: Tensor) -> Tensor:
        if points.shape[-1] != 3:
            raise ValueError(f"texture field points must be (..., 3), got {tuple(points.shape)}")
        r = self.config.bound
        param = self.mlp[0].weight
        unit = (points.to(param.dtype) + r) / (2 * r)
        features = self.encoding(unit).to(param.dtype)
        return torch.sigmoid(self.mlp(features))


# Warm starts of a texture field by regression onto known surface colours: when DMTet takes over from the NeRF
# (colours = the NeRF's albedo near the initial surface) and when refining an existing asset (colours = its
# baked texture at surface samples).


def fit_colour_field(field: TextureField, points: Tensor, colours: Tensor, steps: int, generator: torch.Generator,
                     lr: float = 1e-2, batch: int = 1 << 13) -> float:
    """``steps`` Adam steps of MSE on random minibatches; returns the final full-set MSE."""
    if points.shape != colours.shape or points.shape[-1] != 3:
        raise ValueError(f"points {tuple(points.shape)} and colours {tuple(colours.shape)} must both be (N, 3)")
    if points.shape[0] == 0:
        raise ValueError("no surface points to fit the texture field to")
    opt = torch.optim.Adam(field.parameters(), lr=lr, betas=(0.9, 0.99), eps=1e-15)
    n = points.shape[0]
    for _ in range(steps):
        idx = torch.randint(0, n, (min(batch, n),), generator=generator).to(points.device)
        loss = (field(points[idx]) - colours[idx]).pow(2).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    with torch.no_grad():
        return float(torch.cat([(field(p) - c).pow(2) for p, c in zip(points.split(1 << 16),
                                                                     colours.split(1 << 16), strict=True)]).mean())


def jittered_surface_points(vertices: Tensor, count: int, scale: float, generator: torch.Generator) -> Tensor:
    """``count`` points scattered ±``scale`` around random mesh vertices: the shell the field is
    queried in while the surface moves."""
    idx = torch.randint(0, vertices.shape[0], (count,), generator=generator)
    noise = (torch.rand((count, 3), generator=generator) * 2 - 1) * scale
    return vertices.detach()[idx.to(vertices.device)] + noise.to(vertices)
