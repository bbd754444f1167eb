"""Noise schedule, weighting and timestep sampling with annealing."""

from __future__ import annotations

import pytest
import torch

from morpheus_core.guidance.diffusion import (
    NoiseSchedule,
    NoiseScheduleConfig,
    TimestepRange,
    apply_cfg,
    sample_timesteps,
)
from morpheus_core.guidance.presets import nerf_t_range


def test_alpha_bar_matches_diffusers_scaled_linear() -> None:
    DDPMScheduler = pytest.importorskip("diffusers").DDPMScheduler

    ref = DDPMScheduler(beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear").alphas_cumprod
    ours = NoiseSchedule().alphas_cumprod
    assert ours.shape == (1000,)
    assert torch.allclose(ours.float(), ref.float(), rtol=1e-5)
    assert (ours[1:] < ours[:-1]).all() and 0 < ours[-1] < ours[0] < 1


def test_add_noise_and_weights() -> None:
    s = NoiseSchedule()
    g = torch.Generator().manual_seed(0)
    x0, eps = torch.randn(4, 3, 8, 8, generator=g), torch.randn(4, 3, 8, 8, generator=g)
    t = torch.tensor([0, 10, 500, 999])
    xt = s.add_noise(x0, eps, t)
    ab = s.alphas_cumprod[t].float().reshape(-1, 1, 1, 1)
    assert torch.allclose(xt, ab.sqrt() * x0 + (1 - ab).sqrt() * eps, atol=1e-6)
    w = s.weight(t, "one_minus_alpha_bar")
    assert torch.allclose(w, 1 - ab.flatten()) and (w > 0).all() and (w < 1).all()
    assert torch.equal(s.weight(t, "uniform"), torch.ones(4))
    with pytest.raises(ValueError):
        s.weight(t, "sqrt")


@pytest.mark.parametrize("bad", [torch.tensor([-1]), torch.tensor([1000]), torch.tensor([0.5])])
def test_bad_timesteps_raise(bad: torch.Tensor) -> None:
    with pytest.raises((ValueError, TypeError)):
        NoiseSchedule().alpha_bar(bad)


def test_bad_schedule_config_raises() -> None:
    with pytest.raises(ValueError):
        NoiseSchedule(NoiseScheduleConfig(beta_start=0.02, beta_end=0.01))


def test_cfg() -> None:
    u, c = torch.randn(5), torch.randn(5)
    assert torch.allclose(apply_cfg(u, c, 1.0), c)
    assert torch.allclose(apply_cfg(u, c, 3.0), u + 3 * (c - u))


def test_paper_nerf_annealing() -> None:
    r = nerf_t_range(5000)
    assert r.integer_bounds(0, 1000) == (20, 980)
    assert r.integer_bounds(4999, 1000) == (20, 980)
    assert r.integer_bounds(5000, 1000) == (20, 500)
    assert r.integer_bounds(9999, 1000) == (20, 500)


def test_linear_annealing_and_sampling_bounds() -> None:
    r = TimestepRange(0.1, 0.9, hi_end=0.5, anneal_start=100, anneal_end=200)
    assert r.bounds(150) == pytest.approx((0.1, 0.7))
    g = torch.Generator().manual_seed(1)
    for step in (0, 150, 300):
        lo, hi = r.integer_bounds(step, 1000)
        t = sample_timesteps(r, step, 2000, 1000, g)
        assert t.min() >= lo and t.max() <= hi
        assert t.min() <= lo + 5 and t.max() >= hi - 5  # the whole range is reached


def test_extreme_ranges() -> None:
    full = TimestepRange(0.0, 1.0)
    assert full.integer_bounds(0, 1000) == (0, 999)
    point = TimestepRange(0.5, 0.5)
    assert torch.all(sample_timesteps(point, 0, 10, 1000) == 500)
    for bad in [dict(lo=0.6, hi=0.5), dict(lo=-0.1), dict(hi=1.5), dict(hi=float("nan"))]:
        with pytest.raises(ValueError):
            TimestepRange(**bad)
