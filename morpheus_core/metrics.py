"""Weight-free image metrics (always available; no model weights)."""

from __future__ import annotations

import math

from torch import Tensor

from morpheus_core.color import rgb_to_lab


def psnr(x: Tensor, y: Tensor, max_value: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB over all elements; inf for identical inputs."""
    if x.shape != y.shape:
        raise ValueError(f"PSNR inputs differ in shape: {tuple(x.shape)} vs {tuple(y.shape)}")
    mse = float((x.double() - y.double()).pow(2).mean())
    if not math.isfinite(mse):
        raise ValueError("PSNR input holds NaN/Inf")
    if mse == 0.0:
        return math.inf
    return 10.0 * math.log10(max_value**2 / mse)


def mean_colour_error(x: Tensor, y: Tensor) -> float:
    """ΔE*76 between the mean L*a*b* colours of two images: the low-frequency colour deviation."""
    lab_x = rgb_to_lab(x).mean(dim=(-2, -1))
    lab_y = rgb_to_lab(y).mean(dim=(-2, -1))
    return float((lab_x - lab_y).pow(2).sum(dim=-1).sqrt().mean())
