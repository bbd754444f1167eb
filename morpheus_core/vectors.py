"""Vector helpers for every layer (cameras, fields, meshes, renderers)."""

from __future__ import annotations

import torch
from torch import Tensor

# Normalising a zero-length vector (a degenerate face's normal, an isolated vertex) must not produce NaN.
_NORMAL_EPS = 1e-20


def safe_normalize(v: Tensor, eps: float = _NORMAL_EPS) -> Tensor:
    """v / |v| along the last dim; zero vectors stay zero and their gradient stays finite."""
    return v * torch.rsqrt((v * v).sum(-1, keepdim=True).clamp_min(eps))
