"""Render-target (proxy) prior: ε̂ = (x_t − α_t·x_target)/σ_t for a target-image callable.

It is the exact noise prediction of a denoiser that believes the clean image is ``x_target``,
so its SDS residual is (α_t/σ_t)(x0 − x_target): a known, noise-free pull towards the target.
Two corruptions model the priors of the paper: ``LowPass`` (a "3D prior" that lacks high
frequencies) and ``ColourDeviation`` (a "2D prior" whose low band is tinted and hue-shifted).
Without an ``error`` model the prior has no unconditional branch (ε_u = ε_c), so CFG leaves its
prediction unchanged; with one (``DenoiserError``) x̂0 errs like a real denoiser's, differently for
every noise draw, and CFG extrapolates from an unconditional branch.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from morpheus_core.color import rotate_hue
from morpheus_core.guidance.diffusion import NoiseSchedule
from morpheus_core.guidance.frequency import BandMask, filter_residual
from morpheus_core.guidance.prior_protocol import PixelSpacePrior
from morpheus_core.priors.proxy.denoiser_error import DenoiserError

TargetFn = Callable[[Any], Tensor]

# σ_t never reaches 0 on a discrete schedule (t = 0 gives σ ≈ 0.03); the floor only guards
# custom schedules.
_MIN_SIGMA = 1e-4


@dataclass(frozen=True)
class LowPass:
    """Keep only the low band ``[:B, :B]``, B = int(r·D): detail above it is lost."""

    r: float = 0.6

    def apply(self, target: Tensor) -> Tensor:
        return filter_residual(target, BandMask.low_pass(self.r))


@dataclass(frozen=True)
class ColourDeviation:
    """A smooth tint and hue shift confined to the low band ``r`` of the target."""

    r: float = 0.15
    hue_degrees: float = 30.0
    tint: tuple[float, float, float] = (0.06, 0.0, -0.06)

    def apply(self, target: Tensor) -> Tensor:
        if target.shape[-3] != 3:
            raise ValueError("colour deviation needs RGB targets (3 channels at dim -3)")
        tint = torch.tensor(self.tint, dtype=target.dtype, device=target.device).reshape(3, 1, 1)
        deviated = rotate_hue(target, self.hue_degrees) + tint
        return target + filter_residual(deviated - target, BandMask.low_pass(self.r))


Corruption = LowPass | ColourDeviation


class ProxyPrior(PixelSpacePrior):
    """Pixel-space prior pulling renders towards ``target_fn(condition)`` (optionally corrupted).

    ``target_fn`` returns the clean target for the condition (a camera, or anything the caller
    uses to render the known object), shaped like the noisy input or broadcastable to it.
    ``error`` (with ``current_fn``, the renders that were noised) makes x̂0 err like a real
    denoiser's: the step's noise ε = (x_t − α_t·x0)/σ_t is recovered from the renders and drives it.
    """

    def __init__(
        self, target_fn: TargetFn, schedule: NoiseSchedule, corruption: Corruption | None = None,
        error: DenoiserError | None = None, current_fn: TargetFn | None = None,
    ) -> None:
        if error is not None and current_fn is None:
            raise ValueError("a denoiser error model needs current_fn (the renders that were noised)")
        self.target_fn = target_fn
        self.schedule = schedule
        self.corruption = corruption
        self.error = error
        self.current_fn = current_fn

    def target(self, condition: Any) -> Tensor:
        target = self.target_fn(condition)
        return self.corruption.apply(target) if self.corruption is not None else target

    def predict_noise(self, noisy: Tensor, t: Tensor, condition: Any, cfg_scale: float) -> Tensor:
        if not math.isfinite(cfg_scale):
            raise ValueError(f"cfg_scale must be finite, got {cfg_scale}")
        ab = self.schedule.alpha_bar(t, like=noisy)
        x_t = noisy.to(ab.dtype)
        x0 = self.target(condition).to(device=noisy.device, dtype=ab.dtype)
        sigma = (1.0 - ab).sqrt().clamp(min=_MIN_SIGMA)
        if self.error is not None:
            x0 = self.error.predictions(x0.expand_as(x_t), _step_noise(x_t, ab, sigma, self.current_fn(condition)),
                                        ab, cfg_scale)
        return ((x_t - ab.sqrt() * x0) / sigma).to(noisy.dtype)


def _step_noise(x_t: Tensor, ab: Tensor, sigma: Tensor, renders: Tensor) -> Tensor:
    """ε of x_t = α_t·x0 + σ_t·ε, with x0 the renders that were noised."""
    return (x_t - ab.sqrt() * renders.to(device=x_t.device, dtype=x_t.dtype)) / sigma


def constant_target(image: Tensor) -> TargetFn:
    """A target callable that ignores the condition (one fixed view, as in the 2-D demo)."""
    fixed = image.detach()
    return lambda _condition: fixed


class CurrentRenderCounterpart(PixelSpacePrior):
    """The VSD counterpart of a proxy prior: ε_φ = (x_t − α_t·x̂)/σ_t with x̂ the current render.

    VSD fine-tunes ε_φ to model the distribution of the current renders; for a deterministic
    render that model's ideal is exactly this expression, with nothing left to learn. So with a
    noise-free proxy target, VSD's residual α_t/σ_t·(x0 − x_target) equals SDS's: the proxy runs
    every VSD configuration correctly, and only real priors show the two apart. With the frozen
    prior's ``error`` model, x̂ also carries the share of its noise-driven error that a LoRA copy of
    the same network repeats (``DenoiserError.counterpart_shared``): VSD's control variate.
    ``current_fn(condition)`` returns the (detached) renders of this step.
    """

    def __init__(self, current_fn: TargetFn, schedule: NoiseSchedule, error: DenoiserError | None = None) -> None:
        self.current_fn = current_fn
        self.schedule = schedule
        self.error = error

    def predict_noise(self, noisy: Tensor, t: Tensor, condition: Any, cfg_scale: float) -> Tensor:
        if not math.isfinite(cfg_scale):
            raise ValueError(f"cfg_scale must be finite, got {cfg_scale}")
        ab = self.schedule.alpha_bar(t, like=noisy)
        x_t = noisy.to(ab.dtype)
        sigma = (1.0 - ab).sqrt().clamp(min=_MIN_SIGMA)
        x0 = self.current_fn(condition).to(device=noisy.device, dtype=ab.dtype).expand_as(x_t)
        if self.error is not None:
            x0 = self.error.counterpart_prediction(x0, _step_noise(x_t, ab, sigma, x0), ab)
        return ((x_t - ab.sqrt() * x0) / sigma).to(noisy.dtype)
