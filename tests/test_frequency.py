"""DCT, band masks, filtered residuals, the frequency reference loss and spectra."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from morpheus_core.guidance.frequency import (
    BandMask,
    apply_band,
    band_bound,
    dct2,
    dct_matrix,
    filter_residual,
    frequency_reference_loss,
    high_frequency_ratio,
    idct2,
    radial_psd,
)

SHAPES = [(1, 1), (2, 3), (7, 7), (8, 8), (5, 12), (16, 9), (31, 33), (64, 64), (130, 77)]


def _rand(*shape: int, dtype=torch.float64, seed: int = 0) -> torch.Tensor:
    return torch.randn(*shape, generator=torch.Generator().manual_seed(seed), dtype=dtype)


@pytest.mark.parametrize("n", [1, 2, 5, 8, 17, 64])
def test_dct_matrix_is_orthonormal(n: int) -> None:
    c = dct_matrix(n)
    assert torch.allclose(c @ c.T, torch.eye(n, dtype=torch.float64), atol=1e-13)
    assert torch.allclose(c.T @ c, torch.eye(n, dtype=torch.float64), atol=1e-13)


@pytest.mark.parametrize("h,w", SHAPES)
@pytest.mark.parametrize("method", ["matrix", "fft"])
def test_parseval_and_round_trip_fp64(h: int, w: int, method: str) -> None:
    x = _rand(3, 2, h, w, seed=h * 100 + w)
    u = dct2(x, method)
    assert u.shape == x.shape
    # Parseval per channel: the transform preserves the energy of every H×W slice.
    assert torch.allclose(u.pow(2).sum((-2, -1)), x.pow(2).sum((-2, -1)), rtol=1e-12)
    assert (idct2(u, method) - x).abs().max() < 1e-12


@pytest.mark.parametrize("h,w", SHAPES)
@pytest.mark.parametrize("method", ["matrix", "fft"])
def test_round_trip_fp32(h: int, w: int, method: str) -> None:
    x = _rand(2, 3, h, w, dtype=torch.float32, seed=7 + h + w)
    back = idct2(dct2(x, method), method)
    assert back.dtype == torch.float32
    assert (back - x).abs().max() < 1e-5


@pytest.mark.parametrize("h,w", SHAPES)
def test_matrix_and_fft_forms_agree(h: int, w: int) -> None:
    x = _rand(4, h, w, seed=h * w)
    assert torch.allclose(dct2(x, "matrix"), dct2(x, "fft"), atol=1e-12)
    assert torch.allclose(idct2(x, "matrix"), idct2(x, "fft"), atol=1e-12)


def test_dct_matches_definition() -> None:
    """Independent check against the DCT-II sum written out for one coefficient set."""
    x = _rand(5, 6, seed=3)
    u = dct2(x)
    h, w = x.shape
    for k, m in [(0, 0), (1, 2), (4, 5), (3, 0)]:
        s = sum(
            x[i, j] * math.cos(math.pi * k * (2 * i + 1) / (2 * h)) * math.cos(math.pi * m * (2 * j + 1) / (2 * w))
            for i in range(h)
            for j in range(w)
        )
        s *= math.sqrt((1 if k == 0 else 2) / h) * math.sqrt((1 if m == 0 else 2) / w)
        assert abs(float(u[k, m]) - float(s)) < 1e-12


def test_dct_of_constant_is_dc_only() -> None:
    x = torch.full((9, 4), 2.5, dtype=torch.float64)
    u = dct2(x)
    assert abs(float(u[0, 0]) - 2.5 * 6.0) < 1e-12  # 2.5·sqrt(H·W)
    u[0, 0] = 0
    assert u.abs().max() < 1e-12


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_inputs_keep_dtype_and_are_accurate(dtype: torch.dtype) -> None:
    x = _rand(2, 16, 16, dtype=torch.float32, seed=1).to(dtype)
    u = dct2(x)
    assert u.dtype == dtype and torch.isfinite(u).all()
    ref = dct2(x.float())
    assert (u.float() - ref).abs().max() < 0.05 * ref.abs().max()


def test_reduced_precision_matmul_setting_does_not_spoil_matrix_form() -> None:
    x = _rand(3, 32, 32, dtype=torch.float32, seed=11)
    exact = dct2(x.double(), "matrix")
    old = torch.get_float32_matmul_precision()
    try:
        torch.set_float32_matmul_precision("medium")
        u = dct2(x, "matrix")
    finally:
        torch.set_float32_matmul_precision(old)
    assert (u.double() - exact).abs().max() < 1e-5


def test_invalid_inputs_raise() -> None:
    with pytest.raises(ValueError):
        dct2(torch.randn(5))
    with pytest.raises(TypeError):
        dct2(torch.ones(4, 4, dtype=torch.int64))
    with pytest.raises(ValueError):
        dct2(torch.randn(4, 4), method="wavelet")


@settings(max_examples=30, deadline=None)
@given(h=st.integers(1, 40), w=st.integers(1, 40), r=st.floats(0.0, 1.0), seed=st.integers(0, 10_000))
def test_band_projection_properties(h: int, w: int, r: float, seed: int) -> None:
    x = _rand(2, h, w, seed=seed)
    hp, lp = BandMask.high_pass(r), BandMask.low_pass(r)
    once = filter_residual(x, hp)
    # Λ is a projection: applying V Λ Vᵀ twice equals once.
    assert torch.allclose(filter_residual(once, hp), once, atol=1e-10)
    # high_pass(r) + low_pass(r) = full.
    assert torch.allclose(once + filter_residual(x, lp), x, atol=1e-10)
    m_hp, m_lp = hp.mask(h, w), lp.mask(h, w)
    assert not (m_hp & m_lp).any() and (m_hp | m_lp).all()


def test_high_pass_zeroes_exactly_the_low_block() -> None:
    m = BandMask.high_pass(0.6).mask(64, 40)
    assert band_bound(0.6, 64) == 38 and band_bound(0.6, 40) == 24
    assert not m[:38, :24].any()
    assert m[38:, :].all() and m[:, 24:].all()


def test_band_bound_floors_without_float_noise() -> None:
    assert band_bound(0.29, 100) == 29  # plain int(0.29 * 100) gives 28
    assert band_bound(0.6, 64) == 38
    assert band_bound(1.0, 7) == 7 and band_bound(0.0, 7) == 0


@pytest.mark.parametrize("h,w", [(8, 8), (5, 9)])
def test_r_extremes(h: int, w: int) -> None:
    x = _rand(3, h, w, seed=h)
    assert torch.allclose(filter_residual(x, BandMask.high_pass(0.0)), x, atol=1e-12)  # r = 0 → full
    assert filter_residual(x, BandMask.high_pass(1.0)).abs().max() < 1e-12  # r = 1 → null
    assert BandMask.high_pass(0.0).mask(h, w).all()
    assert not BandMask.high_pass(1.0).mask(h, w).any()
    assert torch.equal(filter_residual(x, BandMask.full()), x)
    assert torch.equal(filter_residual(x, BandMask.null()), torch.zeros_like(x))


def test_custom_mask_and_complement() -> None:
    g = torch.Generator().manual_seed(5)
    m = torch.rand(6, 7, generator=g) > 0.5
    band = BandMask.custom(m)
    x = _rand(2, 6, 7, seed=9)
    kept = filter_residual(x, band)
    assert torch.allclose(kept + filter_residual(x, band.complement()), x, atol=1e-12)
    assert torch.allclose(dct2(kept)[..., ~m], torch.zeros(1, dtype=torch.float64), atol=1e-12)
    with pytest.raises(ValueError, match="custom band mask"):
        band.mask(5, 5)
    assert BandMask.high_pass(0.3).complement() == BandMask.low_pass(0.3)
    assert band == BandMask.custom(m.clone()) and hash(band) == hash(BandMask.custom(m.clone()))
    assert band != band.complement() and band != BandMask.full()
    assert BandMask.full().complement() == BandMask.null()


@pytest.mark.parametrize("bad", [-0.1, 1.5, float("nan"), None])
def test_band_rejects_bad_ratio(bad) -> None:
    with pytest.raises(ValueError):
        BandMask("high_pass", bad)
    with pytest.raises(ValueError):
        BandMask("full", 0.5)


def test_reference_loss_matches_explicit_dct_and_parseval() -> None:
    x, y = _rand(2, 3, 12, 10, seed=1), _rand(2, 3, 12, 10, seed=2)
    band = BandMask.high_pass(0.6)
    want = (apply_band(dct2(x), band) - apply_band(dct2(y), band)).pow(2).sum()
    assert torch.allclose(frequency_reference_loss(x, y, band), want, rtol=1e-6)
    per = frequency_reference_loss(x, y, band, reduction="none")
    assert per.shape == (2, 3)
    # Full pass is the spatial squared error (Parseval); the official code's axes bug would not be.
    full = frequency_reference_loss(x, y, BandMask.full())
    assert torch.allclose(full, (x - y).pow(2).sum(), rtol=1e-6)
    assert frequency_reference_loss(x, y, BandMask.null()) == 0
    assert torch.allclose(frequency_reference_loss(x, y, band, "mean"), want / x.numel(), rtol=1e-6)
    with pytest.raises(ValueError, match="shape"):
        frequency_reference_loss(x, y[..., :5], band)


def test_reference_loss_acts_over_spatial_dims_per_channel() -> None:
    """A colour change that is constant over the image lives only in DC: high-pass ignores it."""
    y = _rand(1, 3, 16, 16, seed=4)
    x = y + torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64).reshape(1, 3, 1, 1)
    assert frequency_reference_loss(x, y, BandMask.high_pass(0.1)) < 1e-20
    assert frequency_reference_loss(x, y, BandMask.low_pass(0.1)) > 1.0


def test_radial_psd_and_hf_ratio() -> None:
    n = 64
    xs = torch.arange(n, dtype=torch.float32)
    low = torch.sin(2 * math.pi * 2 * xs / n)[None, :].expand(n, n)  # radius 4/64 of Nyquist... low
    high = torch.sin(2 * math.pi * 28 * xs / n)[None, :].expand(n, n)  # near Nyquist
    radius, psd = radial_psd(low)
    assert radius.shape == psd.shape and torch.isfinite(psd).all()
    assert radius[psd.argmax()] < 0.15
    _, psd_high = radial_psd(high)
    assert radius[psd_high.argmax()] > 0.8
    assert high_frequency_ratio(low) < 0.01 and high_frequency_ratio(high) > 0.99
    assert high_frequency_ratio(torch.ones(3, 16, 16)) == 0.0
    noise = torch.rand(3, 32, 32, generator=torch.Generator().manual_seed(0))
    assert 0.5 < high_frequency_ratio(noise) < 0.95  # white noise: energy spread by area
    with pytest.raises(ValueError):
        high_frequency_ratio(noise, cutoff=1.5)
