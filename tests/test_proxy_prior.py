"""The render-target prior and its two corruptions."""

from __future__ import annotations

import torch

from morpheus_core.guidance.diffusion import NoiseSchedule
from morpheus_core.guidance.frequency import BandMask, filter_residual
from morpheus_core.metrics.image import mean_colour_error
from morpheus_core.priors import Prior
from morpheus_core.priors.proxy.prior import ColourDeviation, LowPass, ProxyPrior, constant_target


def _image(seed: int, size: int = 24) -> torch.Tensor:
    return torch.rand(1, 3, size, size, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def test_sds_residual_is_the_scaled_pull_to_the_target() -> None:
    s = NoiseSchedule()
    target, x0 = _image(0), _image(1)
    prior = ProxyPrior(constant_target(target), s)
    assert isinstance(prior, Prior)
    g = torch.Generator().manual_seed(2)
    for t in (0, 20, 500, 999):
        tt = torch.tensor([t])
        eps = torch.randn(x0.shape, generator=g, dtype=torch.float64)
        pred = prior.predict_noise(s.add_noise(x0, eps, tt), tt, None, cfg_scale=3.0)
        ab = s.alphas_cumprod[t]
        want = eps + (ab.sqrt() / (1 - ab).sqrt()) * (x0 - target)
        assert torch.allclose(pred, want, atol=1e-9)
        # At the target itself the prediction is exactly the sampled noise (nothing to pull).
        pred_at_target = prior.predict_noise(s.add_noise(target, eps, tt), tt, None, 1.0)
        assert torch.allclose(pred_at_target, eps, atol=1e-9)


def test_low_pass_corruption_removes_exactly_the_high_band() -> None:
    y = _image(3)
    out = LowPass(0.6).apply(y)
    assert filter_residual(out, BandMask.high_pass(0.6)).abs().max() < 1e-12
    assert torch.allclose(filter_residual(out, BandMask.low_pass(0.6)), filter_residual(y, BandMask.low_pass(0.6)))


def test_colour_deviation_lives_in_the_low_band_only() -> None:
    y = _image(4, size=32)
    dev = ColourDeviation(r=0.15, hue_degrees=40.0)
    out = dev.apply(y)
    high = BandMask.high_pass(0.15)
    assert torch.allclose(filter_residual(out, high), filter_residual(y, high), atol=1e-12)
    assert mean_colour_error(out.clamp(0, 1), y) > 2.0  # a visible colour cast


def test_prior_applies_its_corruption_to_the_target() -> None:
    y = _image(5)
    prior = ProxyPrior(constant_target(y), NoiseSchedule(), LowPass(0.3))
    assert torch.allclose(prior.target(None), LowPass(0.3).apply(y))
    assert torch.equal(prior.encode(y), y) and torch.equal(prior.decode(y), y)
