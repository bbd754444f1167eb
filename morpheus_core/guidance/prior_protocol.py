"""The interface every diffusion prior implements, real (Zero123, image-prompt 2D) or proxy: what the guidance
drives, so it lives with the guidance and the priors import it."""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

from torch import Tensor


@runtime_checkable
class Prior(Protocol):
    """A noise predictor ε(x_t, t, condition) in its own space (latents or pixels).

    ``encode`` maps renders (B×3×H×W, values in [0, 1]) into that space and must be
    differentiable, because the guidance gradient flows back through it to the render.
    ``predict_noise`` applies classifier-free guidance itself so that a real model can batch
    its conditional and unconditional branches into one forward.
    """

    def encode(self, images: Tensor) -> Tensor: ...

    def decode(self, latents: Tensor) -> Tensor: ...

    def predict_noise(self, noisy: Tensor, t: Tensor, condition: Any, cfg_scale: float) -> Tensor: ...


class PixelSpacePrior:
    """Mixin for priors that work directly on images: encode/decode are the identity."""

    def encode(self, images: Tensor) -> Tensor:
        return images

    def decode(self, latents: Tensor) -> Tensor:
        return latents
