"""Weight-free image QA metrics: masked PSNR/SSIM, silhouette IoU, HF ratio, colour deviation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from skimage.metrics import structural_similarity

from morpheus_core.metrics.colour_deviation import colour_deviation
from morpheus_core.metrics.image import (
    EmptyRegionError,
    MetricInputError,
    hf_ratio,
    mask_iou,
    masked_psnr,
    masked_ssim,
    mean_colour_error,
    psnr,
    ssim,
)


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _rand(*shape: int, seed: int) -> torch.Tensor:
    return torch.rand(*shape, generator=_gen(seed), dtype=torch.float64)


def _blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur (reflect padding) of a (…, C, H, W) image."""
    radius = max(1, math.ceil(3 * sigma))
    r = torch.arange(-radius, radius + 1, dtype=img.dtype)
    g = torch.exp(-0.5 * (r / sigma) ** 2)
    g = g / g.sum()
    x = img.reshape(-1, 1, *img.shape[-2:])
    x = F.conv2d(F.pad(x, (radius, radius, 0, 0), mode="reflect"), g.view(1, 1, 1, -1))
    x = F.conv2d(F.pad(x, (0, 0, radius, radius), mode="reflect"), g.view(1, 1, -1, 1))
    return x.reshape(img.shape)


def _textured(h: int, w: int, seed: int) -> torch.Tensor:
    """A random texture with detail at every scale: noise plus a lightly blurred copy."""
    noise = _rand(3, h, w, seed=seed)
    return (0.5 * noise + 0.5 * _blur(_rand(3, h, w, seed=seed + 1), 2.0)).clamp(0, 1)


# -- PSNR ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_masked_psnr_known_answer(seed: int) -> None:
    x = _rand(3, 24, 32, seed=seed)
    mask = (_rand(1, 24, 32, seed=seed + 100) > 0.5).double()
    delta = 0.05 + 0.1 * float(_rand(1, seed=seed + 200))
    y = x + delta * mask  # every inside pixel off by delta in every channel; outside untouched
    inside, outside = masked_psnr(x, y, mask)
    assert inside == pytest.approx(10 * math.log10(1 / delta**2), abs=1e-9)
    assert outside == math.inf  # identical region: inf by contract, not NaN


def test_masked_psnr_soft_mask_is_a_weighted_mse() -> None:
    x, y = _rand(2, 3, 16, 16, seed=3), _rand(2, 3, 16, 16, seed=4)
    m = _rand(2, 1, 16, 16, seed=5)
    sq = (x - y).pow(2).mean(dim=1, keepdim=True)
    want_in = 10 * math.log10(1 / float((sq * m).sum() / m.sum()))
    want_out = 10 * math.log10(1 / float((sq * (1 - m)).sum() / (1 - m).sum()))
    inside, outside = masked_psnr(x, y, m)
    assert inside == pytest.approx(want_in, abs=1e-9) and outside == pytest.approx(want_out, abs=1e-9)
    # A full mask is plain PSNR; a 2-D mask applies to every image of the batch.
    assert masked_psnr(x, y, torch.ones(16, 16))[0] == pytest.approx(psnr(x, y), abs=1e-9)


def test_masked_psnr_empty_regions_are_none() -> None:
    x, y = _rand(3, 8, 8, seed=6), _rand(3, 8, 8, seed=7)
    inside, outside = masked_psnr(x, y, torch.zeros(1, 8, 8))
    assert inside is None and outside == pytest.approx(psnr(x, y))
    inside, outside = masked_psnr(x, y, torch.ones(8, 8, dtype=torch.bool))
    assert inside == pytest.approx(psnr(x, y)) and outside is None


def test_masked_psnr_rejects_bad_input() -> None:
    x = _rand(3, 8, 8, seed=8)
    bad = x.clone()
    bad[1, 2, 3] = float("nan")
    with pytest.raises(ValueError, match="y holds NaN"):
        masked_psnr(x, bad, torch.ones(8, 8))
    mask = torch.ones(8, 8)
    mask[0, 0] = float("inf")
    with pytest.raises(MetricInputError, match="mask holds NaN"):
        masked_psnr(x, x, mask)
    with pytest.raises(MetricInputError, match=r"mask values must lie in \[0, 1\]"):
        masked_psnr(x, x, torch.full((8, 8), 2.0))
    with pytest.raises(MetricInputError, match="differ in shape"):
        masked_psnr(x, x[:, :4], torch.ones(8, 8))
    with pytest.raises(MetricInputError, match="mask must be"):
        masked_psnr(x, x, torch.ones(4, 4))


def test_existing_metrics_unchanged() -> None:
    x = _rand(3, 8, 8, seed=9)
    assert psnr(x, x) == math.inf
    assert psnr(x, x + 0.1) == pytest.approx(20.0)
    assert mean_colour_error(x, x) == pytest.approx(0.0, abs=1e-5)


# -- SSIM ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(("seed", "h", "w", "noise"), [(0, 24, 24, 0.05), (1, 33, 41, 0.2), (2, 11, 19, 0.5)])
def test_ssim_matches_scikit_image(seed: int, h: int, w: int, noise: float) -> None:
    x = _textured(h, w, seed)
    y = (x + noise * torch.randn(3, h, w, generator=_gen(seed + 50), dtype=torch.float64)).clamp(0, 1)
    want = structural_similarity(x.numpy(), y.numpy(), channel_axis=0, gaussian_weights=True, sigma=1.5,
                                 use_sample_covariance=False, data_range=1.0)
    assert ssim(x, y) == pytest.approx(want, abs=1e-4)
    assert ssim(x.float(), y.float()) == pytest.approx(want, abs=1e-4)


def test_ssim_batches_average_their_images() -> None:
    xs, ys = _rand(3, 3, 20, 20, seed=10), _rand(3, 3, 20, 20, seed=11)
    per_image = [ssim(xs[i], ys[i]) for i in range(3)]
    assert ssim(xs, ys) == pytest.approx(sum(per_image) / 3, abs=1e-12)


def test_ssim_identical_and_constant_images() -> None:
    x = _rand(2, 3, 16, 16, seed=12)
    assert ssim(x, x) == pytest.approx(1.0, abs=1e-6)
    a, b = 0.2 + 0.6 * float(_rand(1, seed=13)), 0.1 + 0.3 * float(_rand(1, seed=14))
    # Constant images: zero variances, so SSIM is the luminance term (2ab + C1)/(a² + b² + C1), finite.
    c1 = 0.01**2
    want = (2 * a * b + c1) / (a * a + b * b + c1)
    ca, cb = torch.full((3, 12, 12), a, dtype=torch.float64), torch.full((3, 12, 12), b, dtype=torch.float64)
    assert ssim(ca, cb) == pytest.approx(want, abs=1e-12)
    assert ssim(ca, ca) == pytest.approx(1.0, abs=1e-12)


def test_masked_ssim_regions() -> None:
    x = _textured(32, 40, 15)
    y = x.clone()
    y[:, :, 20:] = _rand(3, 32, 20, seed=16)  # columns ≥ 20 differ, the rest is identical
    mask = torch.zeros(1, 32, 40)
    mask[:, :, :15] = 1.0  # window centres ≤ 14 see only columns ≤ 19: SSIM exactly 1 there
    inside, outside = masked_ssim(x, y, mask)
    assert inside == pytest.approx(1.0, abs=1e-9)
    assert outside is not None and outside < 0.9
    assert ssim(x, y, mask) == pytest.approx(inside, abs=1e-12)
    full_in, full_out = masked_ssim(x, y, torch.ones(32, 40))
    assert full_in == pytest.approx(ssim(x, y), abs=1e-12) and full_out is None
    empty_in, empty_out = masked_ssim(x, y, torch.zeros(32, 40))
    assert empty_in is None and empty_out == pytest.approx(ssim(x, y), abs=1e-12)


def test_ssim_failure_paths() -> None:
    x = _rand(3, 16, 16, seed=17)
    border_only = torch.zeros(16, 16)
    border_only[:, :5] = 1.0  # no valid 11×11 window is centred in the first 5 columns
    with pytest.raises(EmptyRegionError):
        ssim(x, x, border_only)
    with pytest.raises(MetricInputError, match="at least 11×11"):
        ssim(x[:, :8], x[:, :8])
    with pytest.raises(MetricInputError, match="odd"):
        ssim(x, x, window=10)
    bad = x.clone()
    bad[0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="x holds NaN"):
        ssim(bad, x)


# -- mask IoU ------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_mask_iou_rectangles(seed: int) -> None:
    rng = np.random.default_rng(seed)
    r0, c0, r1, c1 = (int(v) for v in rng.integers(2, 20, size=4))
    a, b = torch.zeros(1, 40, 40), torch.zeros(40, 40)
    a[0, r0 : r0 + 15, c0 : c0 + 10] = 0.9
    b[r1 : r1 + 12, c1 : c1 + 14] = 0.6
    inter = max(0, min(r0 + 15, r1 + 12) - max(r0, r1)) * max(0, min(c0 + 10, c1 + 14) - max(c0, c1))
    assert mask_iou(a, b) == pytest.approx(inter / (150 + 168 - inter))


def test_mask_iou_edge_cases() -> None:
    empty = torch.zeros(8, 8)
    full = torch.ones(1, 1, 8, 8)
    assert mask_iou(empty, empty) == 1.0
    assert mask_iou(empty, full) == 0.0
    assert mask_iou(torch.full((8, 8), 0.5), full) == 0.0  # the threshold is strict: 0.5 is background
    with pytest.raises(MetricInputError, match="differ in shape"):
        mask_iou(empty, torch.zeros(8, 9))
    nan = empty.clone()
    nan[3, 3] = float("nan")
    with pytest.raises(ValueError, match="b holds NaN"):
        mask_iou(empty, nan)


# -- HF ratio ------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1])
def test_hf_ratio_blur_lowers_it(seed: int) -> None:
    ref = _textured(64, 64, seed)
    assert hf_ratio(ref, ref) == pytest.approx(1.0, abs=1e-12)
    soft, blurred = _blur(ref, 0.8), _blur(ref, 2.0)
    r_soft, r_blur = hf_ratio(soft, ref), hf_ratio(blurred, ref)
    assert r_blur < r_soft < 0.7 and r_blur < 0.1
    # Noisier views carry more high frequencies than a smooth reference.
    noisy = (soft + 0.1 * torch.randn(3, 64, 64, generator=_gen(seed + 9), dtype=torch.float64)).clamp(0, 1)
    assert hf_ratio(noisy, soft) > 1.2
    # The result is the mean of the per-view ratios.
    both = hf_ratio(torch.stack([soft, blurred]), ref)
    assert both == pytest.approx((r_soft + r_blur) / 2, rel=1e-9)


def test_hf_ratio_masks_ignore_the_background() -> None:
    ref = _textured(48, 48, 20)
    mask = torch.zeros(1, 48, 48)
    mask[:, 8:40, 10:38] = 1.0
    plain = hf_ratio(_blur(ref, 1.5), ref, mask=mask, reference_mask=mask)
    garbage = _rand(3, 48, 48, seed=21)
    view = torch.where(mask > 0.5, _blur(ref, 1.5), garbage)
    ref_bg = torch.where(mask > 0.5, ref, 1.0 - garbage)
    assert hf_ratio(view, ref_bg, mask=mask, reference_mask=mask) == pytest.approx(plain, rel=1e-6)
    assert plain is not None and plain < 0.5
    # A view with an empty mask is left out; all views empty or an empty reference mask → None.
    views = torch.stack([view, garbage])
    masks = torch.stack([mask, torch.zeros_like(mask)])
    assert hf_ratio(views, ref_bg, mask=masks, reference_mask=mask) == pytest.approx(plain, rel=1e-6)
    assert hf_ratio(view, ref, mask=torch.zeros(48, 48), reference_mask=mask) is None
    assert hf_ratio(view, ref, mask=mask, reference_mask=torch.zeros(48, 48)) is None


def test_hf_ratio_flat_reference_and_bad_input() -> None:
    view = _textured(32, 32, 22)
    assert hf_ratio(view, torch.full((3, 32, 32), 0.4)) is None
    with pytest.raises(MetricInputError, match="both mask and reference_mask"):
        hf_ratio(view, view, mask=torch.ones(32, 32))
    with pytest.raises(MetricInputError, match="32×32 but the reference is 16×16"):
        hf_ratio(view, view[:, :16, :16])
    with pytest.raises(MetricInputError, match="cutoff"):
        hf_ratio(view, view, cutoff=1.0)
    bad = view.clone()
    bad[0, 0, 0] = float("inf")
    with pytest.raises(ValueError, match="reference holds NaN/Inf"):
        hf_ratio(view, bad)


# -- colour deviation ----------------------------------------------------------------------------


def _object(seed: int, h: int = 40, w: int = 40) -> tuple[torch.Tensor, torch.Tensor]:
    img = 0.15 + 0.6 * _textured(h, w, seed)  # away from 0 and 1 so a tint is never clipped
    mask = torch.zeros(1, h, w)
    mask[:, 5 : h - 5, 8 : w - 6] = 1.0
    return img, mask


def test_colour_deviation_identical_and_monotone_tints() -> None:
    ref, mask = _object(30)
    assert colour_deviation(ref, mask, ref, mask) == pytest.approx(0.0, abs=1e-12)
    values = []
    for tint in (0.05, 0.10, 0.15):
        tinted = ref.clone()
        tinted[0] = tinted[0] + tint * mask[0]
        values.append(colour_deviation(tinted, mask, ref, mask))
    assert values[0] > 0.005 and values[0] < values[1] < values[2] <= 1.0
    # Background pixels do not count.
    junk = torch.where(mask > 0.5, ref, _rand(3, 40, 40, seed=31))
    assert colour_deviation(junk, mask, ref, mask) == pytest.approx(0.0, abs=1e-12)


def test_colour_deviation_known_answers() -> None:
    grey, green, red = torch.tensor([0.5, 0.5, 0.5]), torch.tensor([0.1, 0.8, 0.1]), torch.tensor([0.9, 0.1, 0.1])
    mask = torch.ones(1, 10, 10)
    ref = grey.view(3, 1, 1).expand(3, 10, 10).clone()
    half = ref.clone()
    half[:, :, 5:] = green.view(3, 1, 1)
    # Half the view's mass lands in bins the reference leaves empty: BC = sqrt(1 · ½), whatever the split.
    assert colour_deviation(half, mask, ref, mask) == pytest.approx(1 - math.sqrt(0.5), abs=1e-9)
    all_red = red.view(3, 1, 1).expand(3, 6, 6)
    assert colour_deviation(all_red, torch.ones(6, 6), ref, mask) == pytest.approx(1.0, abs=1e-12)
    # Views are averaged with equal weight: one grey and one green view give the same half-and-half mix.
    views = torch.stack([ref, green.view(3, 1, 1).expand(3, 10, 10)])
    assert colour_deviation(views, mask, ref, mask) == pytest.approx(1 - math.sqrt(0.5), abs=1e-9)


def test_colour_deviation_empty_masks_and_bad_input() -> None:
    ref, mask = _object(32)
    views = torch.stack([ref, _rand(3, 40, 40, seed=33)])
    masks = torch.stack([mask, torch.zeros_like(mask)])
    assert colour_deviation(views, masks, ref, mask) == pytest.approx(0.0, abs=1e-12)  # the empty view is skipped
    assert colour_deviation(ref, torch.zeros(40, 40), ref, mask) is None
    assert colour_deviation(ref, mask, ref, torch.zeros(40, 40)) is None
    small = F.interpolate(ref[None], size=(20, 20), mode="nearest")[0]
    assert colour_deviation(small, torch.ones(20, 20), ref, torch.ones(40, 40)) < 0.05  # any resolution
    with pytest.raises(MetricInputError, match="bins"):
        colour_deviation(ref, mask, ref, mask, bins=1)
    bad = mask.clone()
    bad[0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="view_masks holds NaN"):
        colour_deviation(ref, bad, ref, mask)
