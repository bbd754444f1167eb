"""Diffusion priors behind one protocol (see ``guidance.prior_protocol.Prior``).

Real priors load from local folders only (``registry.ModelRegistry``): ``zero123.Zero123Prior``
(3D prior), ``image2d.Image2DPrior`` (image-prompt 2D prior with canny ControlNet) and
``lora.ObjectLoras`` (VSD's per-object LoRA counterpart); ``proxy.prior.ProxyPrior`` needs no weights.
Import them from their modules: loading diffusers/transformers is deferred to first use.
"""

from morpheus_core.guidance.prior_protocol import PixelSpacePrior, Prior

__all__ = ["PixelSpacePrior", "Prior"]
