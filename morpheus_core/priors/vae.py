"""The VAE side of a latent prior: renders ↔ latents at the prior's resolution.

Renders are encoded with the posterior mean (``.mode()``) rather than a sample: the SD VAE's
posterior spread is tiny next to the diffusion noise added right after, and the mean keeps a
prior call deterministic and independent of which other objects share the batch.
"""

from __future__ import annotations

from torch import Tensor, nn

from morpheus_core.imaging import composite_batch_on_white, resize_batch
from morpheus_core.priors.runtime import PriorRuntime


class LatentCodec:
    """Differentiable ``encode`` (scaled latents) / ``decode`` around an ``AutoencoderKL``."""

    def __init__(self, vae: nn.Module, resolution: int, runtime: PriorRuntime) -> None:
        factor = 2 ** (len(vae.config.block_out_channels) - 1)
        if resolution % factor:
            raise ValueError(f"resolution {resolution} is not a multiple of the VAE factor {factor}")
        self.vae = runtime.place(vae, runtime.vae_precision)
        self.resolution = resolution
        self.runtime = runtime
        self.scaling_factor = float(vae.config.scaling_factor)
        # Every optimising step encodes its renders and back-propagates through the encoder: ~650
        # small ops eager, two graph replays under accel='cudagraph'.
        self._encode = runtime.accelerate(self._mean_of)

    def _mean_of(self, x: Tensor) -> Tensor:
        return self.vae.encode(x).latent_dist.mode()

    def _posterior_mean(self, images: Tensor) -> Tensor:
        x = resize_batch(composite_batch_on_white(images), self.resolution)
        x = (x * 2.0 - 1.0).to(device=self.runtime.torch_device, dtype=self.vae.dtype)
        # float32 out, whatever the VAE runs in: the guidance's frequency split acts on these latents.
        return self._encode(x).float()

    def encode(self, images: Tensor) -> Tensor:
        """Renders B×3×H×W in [0, 1] → latents × scaling factor (the diffusion space); differentiable."""
        return self._posterior_mean(images) * self.scaling_factor

    def encode_unscaled(self, images: Tensor) -> Tensor:
        """Latents without the scaling factor (Zero123's reference concat input)."""
        return self._posterior_mean(images)

    def decode(self, latents: Tensor) -> Tensor:
        z = (latents / self.scaling_factor).to(device=self.runtime.torch_device, dtype=self.vae.dtype)
        return ((self.vae.decode(z).sample + 1.0) / 2.0).clamp(0.0, 1.0)
