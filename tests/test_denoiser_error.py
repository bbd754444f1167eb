"""The stochastic oracle's error model: a real denoiser's errors, property by property."""

from __future__ import annotations

import itertools

import pytest
import torch

from morpheus_core.guidance.diffusion import NoiseSchedule
from morpheus_core.guidance.frequency import BandMask, dct2, filter_residual
from morpheus_core.priors.proxy.denoiser_error import DenoiserError
from morpheus_core.priors.proxy.prior import CurrentRenderCounterpart, ProxyPrior

SCHEDULE = NoiseSchedule()
DRIFT = DenoiserError(drift_hue_sd=15.0, drift_tint_sd=0.03)


def _images(seed: int, batch: int = 2, size: int = 32) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    # A smooth image with detail: random low-band colours plus fine texture, like a product render.
    base = torch.nn.functional.interpolate(torch.rand(batch, 3, 4, 4, generator=g, dtype=torch.float64), size=size,
                                           mode="bilinear", align_corners=False)
    return (base + 0.15 * torch.rand(batch, 3, size, size, generator=g, dtype=torch.float64)).clamp(0, 1)


class _Cond:
    def __init__(self, target: torch.Tensor, current: torch.Tensor) -> None:
        self.target, self.current = target, current


def _prior(error: DenoiserError | None) -> ProxyPrior:
    return ProxyPrior(lambda c: c.target, SCHEDULE, error=error, current_fn=lambda c: c.current)


def _x0_hat(prior: ProxyPrior, x0: torch.Tensor, target: torch.Tensor, t: int, eps: torch.Tensor,
            cfg: float = 1.0) -> torch.Tensor:
    """The prediction's x̂0 = (x_t − σ·ε̂)/α for renders ``x0`` noised with ``eps`` at ``t``."""
    tt = torch.full((x0.shape[0],), t)
    xt = SCHEDULE.add_noise(x0, eps, tt)
    pred = prior.predict_noise(xt, tt, _Cond(target, x0), cfg)
    ab = SCHEDULE.alpha_bar(tt, like=x0)
    return (xt - (1 - ab).sqrt() * pred) / ab.sqrt()


def _eps(seed: int, like: torch.Tensor) -> torch.Tensor:
    return torch.randn(like.shape, generator=torch.Generator().manual_seed(seed), dtype=like.dtype)


def test_without_an_error_model_the_prediction_is_the_target() -> None:
    target, x0 = _images(1), _images(2)
    for t in (20, 400):
        assert torch.allclose(_x0_hat(_prior(None), x0, target, t, _eps(3, x0)), target, atol=1e-9)


def test_a_new_noise_draw_gives_a_new_error_and_the_same_draw_the_same() -> None:
    target, x0 = _images(4), _images(5)
    prior = _prior(DRIFT)
    a = _x0_hat(prior, x0, target, 300, _eps(6, x0)) - target
    b = _x0_hat(prior, x0, target, 300, _eps(7, x0)) - target
    again = _x0_hat(prior, x0, target, 300, _eps(6, x0)) - target
    assert torch.allclose(a, again, atol=1e-12)  # a fixed function of x_t, like a network
    assert (a - b).pow(2).mean() > 0.5 * a.pow(2).mean()  # a different guess per draw
    # independent across the views of one call: the two images' errors are uncorrelated
    corr = torch.corrcoef(torch.stack([a[0].flatten(), a[1].flatten()]))[0, 1]
    assert abs(float(corr)) < 0.3


def test_the_error_grows_with_t() -> None:
    target = _images(8, batch=8)
    prior = _prior(DenoiserError())
    rms = []
    for t in (20, 100, 250, 500, 900):
        err = torch.stack([_x0_hat(prior, target, target, t, _eps(s, target)) - target for s in range(4)])
        rms.append(float(err.pow(2).mean().sqrt()))
    assert all(b > a for a, b in itertools.pairwise(rms)), rms
    assert rms[-1] > 2.0 * rms[0]


def test_the_error_is_spatially_correlated_with_its_configured_spectrum() -> None:
    model = DenoiserError()
    size, t = 64, 400
    ab = SCHEDULE.alpha_bar(torch.full((16,), t), like=torch.zeros(16, 3, size, size))
    eps = torch.randn(16, 3, size, size, generator=torch.Generator().manual_seed(9), dtype=torch.float32)
    err = model.noise_error(eps, ab)
    power = dct2(err).pow(2).mean(dim=(0, 1))
    want = model.error_spectrum(ab, size, size)[0, 0]
    # Low frequencies carry far more power than high ones (not white), in the configured ratio.
    low, high = power[:4, :4].mean(), power[32:, 32:].mean()
    assert low > 20 * high
    assert float(low / high) == pytest.approx(float(want[:4, :4].mean() / want[32:, 32:].mean()), rel=0.35)
    # Neighbouring pixels' errors correlate (white noise would give ≈ 0).
    corr = torch.corrcoef(torch.stack([err[..., :-1].flatten(), err[..., 1:].flatten()]))[0, 1]
    assert corr > 0.5


def test_the_colour_drift_changes_per_call_and_leaves_the_high_band_right() -> None:
    target = _images(10, batch=4)
    drifts = [DRIFT.colour_drift(target, _eps(s, target)) for s in (11, 12)]
    for d in drifts:
        assert filter_residual(d, BandMask.high_pass(DRIFT.drift_r)).abs().max() < 1e-9
    # per image and per call: a different mean colour shift
    shift = [d.mean(dim=(-2, -1)) for d in drifts]
    assert (shift[0] - shift[1]).abs().max() > 0.01
    assert (shift[0][0] - shift[0][1]).abs().max() > 0.01
    # and zero on average: the systematic deviation belongs to the role's corruption
    many = torch.cat([DRIFT.colour_drift(target, _eps(s, target)).mean(dim=(-2, -1)) for s in range(40)])
    assert many.mean(dim=0).abs().max() < 0.01 < many.std(dim=0).min()
    assert torch.equal(DenoiserError().colour_drift(target, _eps(0, target)), torch.zeros_like(target))


def test_cfg_changes_the_residual_and_the_branches_differ() -> None:
    target, x0 = _images(13), _images(14)
    prior, eps = _prior(DenoiserError()), _eps(15, x0)
    x1, x3, x5 = (_x0_hat(prior, x0, target, 300, eps, cfg) for cfg in (1.0, 3.0, 5.0))
    # conditional ≠ unconditional: guidance moves the prediction, linearly in the scale
    assert (x3 - x1).abs().max() > 1e-2
    assert torch.allclose(x5 - x1, 2.0 * (x3 - x1), atol=1e-9)
    # what it adds is the target's detail: its mean colour (DC) is untouched
    assert torch.allclose((x3 - x1).mean(dim=(-2, -1)), torch.zeros(2, 3, dtype=x1.dtype), atol=1e-9)


def test_the_vsd_counterpart_shares_its_configured_share_of_the_error() -> None:
    target, x0 = _images(16), _images(17)
    eps = _eps(18, x0)
    for shared in (0.0, 0.5, 1.0):
        model = DenoiserError(counterpart_shared=shared)
        prior = _prior(model)
        counterpart = CurrentRenderCounterpart(lambda c: c.current, SCHEDULE, model)
        t = torch.full((2,), 300)
        xt = SCHEDULE.add_noise(x0, eps, t)
        cond = _Cond(target, x0)
        residual = prior.predict_noise(xt, t, cond, 1.0) - counterpart.predict_noise(xt, t, cond, 1.0)
        ab = SCHEDULE.alpha_bar(t, like=x0)
        error = model.noise_error(eps, ab)
        want = (ab / (1 - ab)).sqrt() * (x0 - target - (1.0 - shared) * error)
        assert torch.allclose(residual, want, atol=1e-8)


def test_bad_parameters_and_a_missing_current_fn_are_refused() -> None:
    with pytest.raises(ValueError, match="uncertainty"):
        DenoiserError(uncertainty=0.0)
    with pytest.raises(ValueError, match="counterpart_shared"):
        DenoiserError(counterpart_shared=1.5)
    with pytest.raises(ValueError, match="spectrum_amplitude"):
        DenoiserError(spectrum_amplitude=float("nan"))
    with pytest.raises(ValueError, match="current_fn"):
        ProxyPrior(lambda c: c, SCHEDULE, error=DenoiserError())


def test_the_oracle_is_stochastic_by_default_and_noise_free_by_name() -> None:
    from benchmarks.oracle import OracleConfig

    default = OracleConfig()
    assert default.kind == "stochastic" and set(default.errors()) == {"3d", "2d"}
    assert default.errors()["2d"].drift_hue_sd > 0 and default.errors()["3d"].drift_hue_sd == 0
    quiet = OracleConfig.named("noise-free")
    assert quiet.kind == "noise-free" and quiet.errors() == {} and "noise-free" in quiet.describe()
    with pytest.raises(ValueError, match="noise-free"):
        OracleConfig.named("perfect")


def test_with_the_error_model_vsd_and_sds_residuals_differ() -> None:
    """The noise-free proxy's VSD residual equals SDS's; the stochastic one's does not (VSD removes the
    counterpart's shared error), so the benchmark can tell the two apart."""
    target, x0 = _images(19), _images(20)
    eps = _eps(21, x0)
    t = torch.full((2,), 250)
    xt = SCHEDULE.add_noise(x0, eps, t)
    cond = _Cond(target, x0)
    for model, differ in ((None, False), (DenoiserError(), True)):
        prior = _prior(model)
        sds = prior.predict_noise(xt, t, cond, 1.0) - eps
        vsd = prior.predict_noise(xt, t, cond, 1.0) - CurrentRenderCounterpart(
            lambda c: c.current, SCHEDULE, model).predict_noise(xt, t, cond, 1.0)
        assert (not torch.allclose(sds, vsd, atol=1e-6)) == differ
