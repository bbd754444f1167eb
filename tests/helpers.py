"""Small deterministic priors for guidance tests (random weights, fixed by a seed)."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from morpheus_core.guidance.prior_protocol import PixelSpacePrior

# The real 2D prior runs at 64 px in CPU tests (512 in the pipeline) to keep them fast.
RES_2D = 64


class RandomPrior(PixelSpacePrior):
    """ε = tanh(a ⊙ x_t + b·t/1000 + c): a random but deterministic noise predictor.

    ``cond`` and ``uncond`` differ (different b), so CFG changes the prediction.
    """

    def __init__(self, shape: tuple[int, ...], seed: int, dtype: torch.dtype = torch.float64) -> None:
        g = torch.Generator().manual_seed(seed)
        self.a = torch.randn(shape, generator=g, dtype=dtype)
        self.b_cond = torch.randn(shape, generator=g, dtype=dtype)
        self.b_uncond = torch.randn(shape, generator=g, dtype=dtype)
        self.c = torch.randn(shape, generator=g, dtype=dtype)

    def _branch(self, x: Tensor, t: Tensor, b: Tensor) -> Tensor:
        tt = t.to(x.dtype).reshape(-1, *([1] * (x.dim() - 1))) / 1000.0
        return torch.tanh(self.a.to(x) * x + b.to(x) * tt + self.c.to(x))

    def predict_noise(self, noisy: Tensor, t: Tensor, condition: Any, cfg_scale: float) -> Tensor:
        cond = self._branch(noisy, t, self.b_cond)
        uncond = self._branch(noisy, t, self.b_uncond)
        return uncond + cfg_scale * (cond - uncond)


class TinyFinetunedPrior(PixelSpacePrior, nn.Module):
    """A trainable counterpart for VSD: one 3×3 convolution with random initial weights."""

    def __init__(self, channels: int, seed: int, dtype: torch.dtype = torch.float64) -> None:
        nn.Module.__init__(self)
        torch.manual_seed(seed)
        self.conv = nn.Conv2d(channels, channels, 3, padding=1).to(dtype)

    def predict_noise(self, noisy: Tensor, t: Tensor, condition: Any, cfg_scale: float) -> Tensor:
        tt = t.to(noisy.dtype).reshape(-1, 1, 1, 1) / 1000.0
        return self.conv(noisy) * (1.0 + tt)


class PooledPrior(RandomPrior):
    """A 'latent' prior: encode is a 2× average pool scaled by 2, so gradients must go through it."""

    def encode(self, images: Tensor) -> Tensor:
        return 2.0 * torch.nn.functional.avg_pool2d(images, 2)

    def decode(self, latents: Tensor) -> Tensor:
        return torch.nn.functional.interpolate(latents / 2.0, scale_factor=2, mode="nearest")


def photo(seed: int, size: int = 64, rgba: bool = True) -> torch.Tensor:
    """A random object photo: a coloured blob with texture on a transparent background."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, size), torch.linspace(-1, 1, size), indexing="ij")
    cx, cy, r = (torch.rand(3, generator=g) * torch.tensor([0.6, 0.6, 0.3]) + torch.tensor([-0.3, -0.3, 0.4]))
    alpha = ((xx - cx) ** 2 + (yy - cy) ** 2 < r**2).float()
    rgb = torch.rand(3, 1, 1, generator=g) * 0.6 + 0.2 + 0.2 * torch.rand(3, size, size, generator=g)
    rgb = rgb.clamp(0, 1)
    return torch.cat([rgb, alpha[None]]) if rgba else rgb * alpha + (1 - alpha)
