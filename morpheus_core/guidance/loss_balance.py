"""The loss balance of the official Morpheus3D code: which terms are sums, which are means, and the scale.

The paper writes every term as a squared norm, but its hyper-parameters (λc = 5e-4, k3D = 1, k2D = 3,
σ = 1) were tuned in the official threestudio-based code, whose reductions are not the norms':

* **prior guidance** (SDS / VSD): the surrogate ``0.5·‖z0 − sg(z0 − g)‖²`` is *summed* over the prior's
  own space (e.g. the 4×32×32 VAE latent) and divided by the number of views, so each latent element
  receives ``λc·k·w(t)·VΛVᵀ(ε − ε_φ)/views`` (``morpheus_core.guidance.hybrid``);
* **reference terms** (RGB MSE, the frequency reference loss ‖Λ(Vᵀx − Vᵀy)‖², the mask BCE): *means*
  over their elements (C·H·W, or H·W for the mask), one reference view per object;
* **regularisers**: means (over pixels, vertices or edges), weighted by their own λ;
* everything multiplied by ``lambda_scale = 1000``.

Derivation of why it matters: with a summed reference term the gradient on one reference pixel is
``2(1 − λc)(x − y)``; with the mean it is ``2(1 − λc)(x − y)/(C·H·W)``. The prior's gradient per latent
element is the same in both. So summing the image terms makes the prior ``C·H·W`` times weaker
against the photo than the paper's λc intends (49 152× at 128 px): the unseen sides barely move.

``LAMBDA_SCALE`` multiplies the 3-D parameters' loss (guidance + the stage's own terms) in
``scaled_total``. Adam is invariant to a constant loss scale, but gradient clipping and the fp16
loss-scale logic are not: with the scale the loss and its gradients have the official magnitudes.
The VSD counterparts' ε-MSE is their own objective (their own optimiser), left unscaled.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from morpheus_core.guidance.frequency import BandMask, frequency_reference_loss

LAMBDA_SCALE = 1000.0


def reference_loss(render: Tensor, reference: Tensor, band: BandMask, objects: int = 1) -> Tensor:
    """‖Λ(Vᵀx − Vᵀy)‖² averaged over each reference view's C·H·W elements and over each object's
    reference views, summed over ``objects`` (object-major rows): each object's term is its own mean."""
    per_view = frequency_reference_loss(render, reference, band, reduction="none").sum(dim=-1)
    elements = render[0].numel()
    return per_view.sum() / (elements * (render.shape[0] // objects))


def mask_bce(opacity: Tensor, mask: Tensor) -> Tensor:
    """BCE of one object's reference-view opacity (B×1×H×W) against its mask, averaged over every
    pixel, as the official code reduces it."""
    o = opacity.float().clamp(1e-5, 1.0 - 1e-5)
    with torch.autocast(o.device.type, enabled=False):  # BCE refuses to autocast: it is float32 here
        return F.binary_cross_entropy(o, mask.float().expand_as(o))


def scaled_total(guidance: Tensor, extra: Tensor, finetune: Tensor) -> Tensor:
    """The step's loss: ``LAMBDA_SCALE``·(guidance + the stage's own terms) + the VSD counterparts' loss."""
    return LAMBDA_SCALE * (guidance + extra) + finetune
