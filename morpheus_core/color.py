"""Colour-space maths on image tensors (…×3×H×W, sRGB in [0, 1])."""

from __future__ import annotations

import math

import torch
from torch import Tensor

_RGB_TO_XYZ = torch.tensor(
    [[0.4124564, 0.3575761, 0.1804375], [0.2126729, 0.7151522, 0.0721750], [0.0193339, 0.1191920, 0.9503041]],
    dtype=torch.float64,
)
_D65_WHITE = (0.95047, 1.0, 1.08883)
_RGB_TO_YIQ = torch.tensor(
    [[0.299, 0.587, 0.114], [0.595716, -0.274453, -0.321263], [0.211456, -0.522591, 0.311135]],
    dtype=torch.float64,
)


def _mix(x: Tensor, mat: Tensor) -> Tensor:
    return torch.einsum("ij,...jhw->...ihw", mat.to(x), x)


def rgb_to_lab(rgb: Tensor) -> Tensor:
    """sRGB (D65) to CIE L*a*b*; the channel dim is -3."""
    if rgb.shape[-3] != 3:
        raise ValueError(f"expected 3 colour channels at dim -3, got shape {tuple(rgb.shape)}")
    x = rgb.float().clamp(0.0, 1.0)
    linear = torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055).pow(2.4))
    xyz = _mix(linear, _RGB_TO_XYZ)
    white = torch.tensor(_D65_WHITE, dtype=xyz.dtype, device=xyz.device).reshape(3, 1, 1)
    t = xyz / white
    eps = (6.0 / 29.0) ** 3
    f = torch.where(t > eps, t.clamp(min=eps).pow(1.0 / 3.0), t / (3 * (6.0 / 29.0) ** 2) + 4.0 / 29.0)
    fx, fy, fz = f.unbind(dim=-3)
    return torch.stack([116.0 * fy - 16.0, 500.0 * (fx - fy), 200.0 * (fy - fz)], dim=-3)


def rotate_hue(rgb: Tensor, degrees: float | Tensor) -> Tensor:
    """Rotate chroma by ``degrees`` in YIQ (luma kept), a linear and smooth hue shift.

    ``degrees`` is one angle, or a tensor of one angle per image of a B×3×H×W batch (no host read)."""
    if not isinstance(degrees, Tensor):
        a = math.radians(degrees)
        rot = torch.tensor(
            [[1.0, 0.0, 0.0], [0.0, math.cos(a), -math.sin(a)], [0.0, math.sin(a), math.cos(a)]], dtype=torch.float64
        )
        mat = torch.linalg.inv(_RGB_TO_YIQ) @ rot @ _RGB_TO_YIQ
        return _mix(rgb, mat)
    if rgb.dim() != 4 or degrees.shape != rgb.shape[:1]:
        raise ValueError(f"per-image angles {tuple(degrees.shape)} need a B×3×H×W batch, got {tuple(rgb.shape)}")
    a = torch.deg2rad(degrees.to(torch.float64))
    cos, sin, one, zero = a.cos(), a.sin(), torch.ones_like(a), torch.zeros_like(a)
    rot = torch.stack([torch.stack([one, zero, zero], -1), torch.stack([zero, cos, -sin], -1),
                       torch.stack([zero, sin, cos], -1)], -2)  # B×3×3
    yiq = _RGB_TO_YIQ.to(a.device)
    mat = torch.linalg.inv(yiq) @ rot @ yiq
    return torch.einsum("bij,bjhw->bihw", mat.to(rgb), rgb)
