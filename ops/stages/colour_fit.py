"""Warm-start a texture field by regression onto known surface colours.

Used twice: when DMTet takes over from the NeRF (colours = the NeRF's albedo near the initial
surface) and when refining an existing asset (colours = its baked texture at surface samples).
"""

from __future__ import annotations

import torch
from torch import Tensor

from morpheus_core.texture import TextureField


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
