"""Weight-free image QA metrics (always available; no model weights): PSNR, SSIM, silhouette IoU, HF ratio.

The other weight-free metrics, ``metrics.colour_deviation`` (which shares this module's argument
checks) and ``metrics.mesh_health``, raise the same ``MetricInputError``.

Image conventions: images are float tensors in [0, 1], (C, H, W) or (N, C, H, W) (C = 3 wherever colour is
involved); masks are (H, W), (1, H, W), (1, 1, H, W) or (N, 1, H, W) in [0, 1]. A mask with one slice
applies to every image of a batch. Soft masks weight pixels (PSNR, SSIM, colour histograms, hf_ratio);
silhouette IoU thresholds them (> 0.5, like ``ops.stages.qa.mask_iou``).

Non-finite values never leave this module silently:

* NaN/Inf inputs raise ``MetricInputError`` (a ``ValueError``) naming the argument;
* an empty region (a mask with zero weight where a mean is needed) gives ``None``, except in ``ssim``,
  whose ``float`` result cannot say "nothing measured" and which raises ``EmptyRegionError`` instead;
* PSNR of identical inputs is ``math.inf`` (the only non-finite value returned, by the usual convention;
  JSON writers in ``assets_store`` already store it as the string "inf").
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from morpheus_core.color import rgb_to_lab
from morpheus_core.guidance.frequency import BandMask, filter_residual, high_frequency_ratio


class MetricInputError(ValueError):
    """A metric was handed an argument of the wrong shape, dtype or range, or holding NaN/Inf."""


class EmptyRegionError(MetricInputError):
    """A metric that must return a number was asked to average over an empty region."""


def psnr(x: Tensor, y: Tensor, max_value: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB over all elements; inf for identical inputs."""
    if x.shape != y.shape:
        raise ValueError(f"PSNR inputs differ in shape: {tuple(x.shape)} vs {tuple(y.shape)}")
    mse = float((x.double() - y.double()).pow(2).mean())
    if not math.isfinite(mse):
        raise ValueError("PSNR input holds NaN/Inf")
    if mse == 0.0:
        return math.inf
    return 10.0 * math.log10(max_value**2 / mse)


def detail_psnr(x: Tensor, y: Tensor, r: float = 0.6) -> float:
    """PSNR of the high band only (DCT indices ≥ r·D per axis, the band the paper's 2D prior adds): how
    well fine detail (print, stripes, weave) is reproduced, whatever the colours and shapes below it."""
    if x.shape != y.shape:
        raise ValueError(f"detail PSNR inputs differ in shape: {tuple(x.shape)} vs {tuple(y.shape)}")
    band = BandMask.high_pass(r)
    return psnr(filter_residual(x.double(), band), filter_residual(y.double(), band))


def mean_colour_error(x: Tensor, y: Tensor) -> float:
    """ΔE*76 between the mean L*a*b* colours of two images: the low-frequency colour deviation."""
    lab_x = rgb_to_lab(x).mean(dim=(-2, -1))
    lab_y = rgb_to_lab(y).mean(dim=(-2, -1))
    return float((lab_x - lab_y).pow(2).sum(dim=-1).sqrt().mean())


# -- input checking ------------------------------------------------------------------------------

# Masks from renderers overshoot [0, 1] by float rounding; anything further out is a caller's bug.
_MASK_SLACK = 1e-4


def _finite(t: object, name: str) -> Tensor:
    """``t`` as a float64 CPU tensor, or a MetricInputError naming ``name``."""
    if not isinstance(t, Tensor):
        raise MetricInputError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if t.dtype == torch.bool:
        t = t.to(torch.float64)
    elif not t.is_floating_point():
        raise MetricInputError(f"{name} must be a floating-point (or bool) tensor, got {t.dtype}")
    t = t.detach().to("cpu", torch.float64)
    if not bool(torch.isfinite(t).all()):
        raise MetricInputError(f"{name} holds NaN/Inf values")
    return t


def checked_images(x: object, name: str, colour: bool = False) -> Tensor:
    """Images checked (finite, non-empty, 3 channels if ``colour``) as (N, C, H, W) float64 from (C, H, W) or
    (N, C, H, W); a MetricInputError naming ``name`` otherwise."""
    t = _finite(x, name)
    if t.dim() == 3:
        t = t.unsqueeze(0)
    if t.dim() != 4 or t.shape[0] == 0 or t.shape[-1] == 0 or t.shape[-2] == 0:
        raise MetricInputError(f"{name} must be (C, H, W) or (N, C, H, W) with N, H, W > 0, got {tuple(x.shape)}")
    if colour and t.shape[1] != 3:
        raise MetricInputError(f"{name} must have 3 colour channels at dim -3, got shape {tuple(x.shape)}")
    return t


def _image_pair(x: object, y: object) -> tuple[Tensor, Tensor]:
    xs, ys = checked_images(x, "x"), checked_images(y, "y")
    if xs.shape != ys.shape:
        raise MetricInputError(f"x and y differ in shape: {tuple(x.shape)} vs {tuple(y.shape)}")
    return xs, ys


def checked_masks(m: object, name: str, n: int | None, h: int, w: int) -> Tensor:
    """Masks checked (finite, in [0, 1], H×W = ``h``×``w``) as (N, 1, H, W) float64; a single mask is repeated
    over the batch of ``n`` (None: keep its own N); a MetricInputError naming ``name`` otherwise."""
    t = _finite(m, name)
    if t.dim() == 2:
        t = t[None, None]
    elif t.dim() == 3:
        t = t.unsqueeze(0) if t.shape[0] == 1 else t.unsqueeze(1)
    if t.dim() != 4 or t.shape[1] != 1 or tuple(t.shape[-2:]) != (h, w) or t.shape[0] == 0:
        raise MetricInputError(f"{name} must be (H, W), (1, H, W) or (N, 1, H, W) with H×W = {h}×{w}, "
                               f"got {tuple(m.shape)}")
    if n is not None and t.shape[0] not in (1, n):
        raise MetricInputError(f"{name} holds {t.shape[0]} masks for {n} images")
    if float(t.min()) < -_MASK_SLACK or float(t.max()) > 1.0 + _MASK_SLACK:
        raise MetricInputError(f"{name} values must lie in [0, 1], got [{float(t.min()):.4g}, {float(t.max()):.4g}]")
    t = t.clamp(0.0, 1.0)
    return t.expand(n, 1, h, w) if n is not None else t


def _mask_2d(m: object, name: str) -> Tensor:
    """A silhouette (or a batch of them) as (N, 1, H, W), whatever layout it came in."""
    if not isinstance(m, Tensor):
        raise MetricInputError(f"{name} must be a torch.Tensor, got {type(m).__name__}")
    if m.dim() < 2:
        raise MetricInputError(f"{name} must have at least 2 dims (H, W), got {tuple(m.shape)}")
    return checked_masks(m, name, None, int(m.shape[-2]), int(m.shape[-1]))


# -- PSNR ----------------------------------------------------------------------------------------


def _weighted_psnr(sq: Tensor, weight: Tensor, channels: int, max_value: float) -> float | None:
    total = float(weight.sum())
    if total <= 0.0:
        return None
    mse = float((sq * weight).sum()) / (total * channels)
    if mse == 0.0:
        return math.inf
    return 10.0 * math.log10(max_value**2 / mse)


def masked_psnr(x: Tensor, y: Tensor, mask: Tensor, max_value: float = 1.0) -> tuple[float | None, float | None]:
    """PSNR (dB) inside and outside ``mask``: the squared error of each pixel is weighted by the mask
    (inside) or 1 − mask (outside), and averaged over the channels and the region's total weight.

    Returns ``(inside, outside)``. A region whose error is exactly zero gives ``math.inf`` (callers
    must handle it, e.g. by capping); a region of zero weight (an all-0 or all-1 mask) gives ``None``.
    """
    if not (math.isfinite(max_value) and max_value > 0):
        raise MetricInputError(f"max_value must be a positive finite number, got {max_value}")
    xs, ys = _image_pair(x, y)
    n, c, h, w = xs.shape
    m = checked_masks(mask, "mask", n, h, w)
    sq = (xs - ys).pow(2).sum(dim=1, keepdim=True)
    return _weighted_psnr(sq, m, c, max_value), _weighted_psnr(sq, 1.0 - m, c, max_value)


# -- SSIM ----------------------------------------------------------------------------------------

_SSIM_K1 = 0.01
_SSIM_K2 = 0.03


def _gaussian_kernel(window: int, sigma: float) -> Tensor:
    if window < 1 or window % 2 == 0:
        raise MetricInputError(f"window must be a positive odd integer, got {window}")
    if not (math.isfinite(sigma) and sigma > 0):
        raise MetricInputError(f"sigma must be positive and finite, got {sigma}")
    r = torch.arange(window, dtype=torch.float64) - (window - 1) / 2
    g = torch.exp(-0.5 * (r / sigma) ** 2)
    return g / g.sum()


def _ssim_map(xs: Tensor, ys: Tensor, window: int, sigma: float, data_range: float) -> Tensor:
    """Per-pixel SSIM (N, C, H − window + 1, W − window + 1): 'valid' windows only.

    Only pixels whose whole window lies inside the image get a value, so no padding convention
    enters the result; this is exactly the region scikit-image averages (it filters with reflect
    padding and then crops (window − 1)/2 pixels from every border)."""
    n, c, h, w = xs.shape
    if h < window or w < window:
        raise MetricInputError(f"SSIM needs images at least {window}×{window} (the window), got {h}×{w}")
    if not (math.isfinite(data_range) and data_range > 0):
        raise MetricInputError(f"data_range must be positive and finite, got {data_range}")
    g = _gaussian_kernel(window, sigma)
    c1, c2 = (_SSIM_K1 * data_range) ** 2, (_SSIM_K2 * data_range) ** 2
    maps = []
    # One image at a time bounds memory: five float64 moment maps per channel.
    for i in range(n):
        x, y = xs[i : i + 1], ys[i : i + 1]
        stack = torch.cat([x, y, x * x, y * y, x * y], dim=1)
        groups = stack.shape[1]
        out = F.conv2d(stack, g.view(1, 1, 1, window).expand(groups, 1, 1, window), groups=groups)
        out = F.conv2d(out, g.view(1, 1, window, 1).expand(groups, 1, window, 1), groups=groups)
        mu_x, mu_y, xx, yy, xy = out.split(c, dim=1)
        var_x, var_y, cov = xx - mu_x * mu_x, yy - mu_y * mu_y, xy - mu_x * mu_y
        num = (2 * mu_x * mu_y + c1) * (2 * cov + c2)
        # c1, c2 > 0 and the variances are ≥ −rounding, so the denominator is positive: no 0/0.
        den = (mu_x * mu_x + mu_y * mu_y + c1) * (var_x + var_y + c2)
        maps.append(num / den)
    return torch.cat(maps)


def _region_means(values: Tensor, weight: Tensor) -> tuple[float | None, float | None]:
    """Weighted means of ``values`` (N, 1, h, w) under weight and 1 − weight; None for zero weight."""
    out: list[float | None] = []
    for wt in (weight, 1.0 - weight):
        total = float(wt.sum())
        out.append(None if total <= 0.0 else float((values * wt).sum()) / total)
    return out[0], out[1]


def _ssim_mean_map(x: Tensor, y: Tensor, window: int, sigma: float, data_range: float) -> Tensor:
    """The SSIM map averaged over channels, (N, 1, h, w)."""
    xs, ys = _image_pair(x, y)
    return _ssim_map(xs, ys, window, sigma, data_range).mean(dim=1, keepdim=True)


def _centre_weights(mask: Tensor, x: Tensor, window: int) -> Tensor:
    """The mask at the SSIM map's pixels: map pixel (i, j) is the window centred on image pixel
    (i + window // 2, j + window // 2)."""
    xs = checked_images(x, "x")
    n, _, h, w = xs.shape
    half = window // 2
    return checked_masks(mask, "mask", n, h, w)[..., half : h - half, half : w - half]


def ssim(x: Tensor, y: Tensor, mask: Tensor | None = None, window: int = 11, sigma: float = 1.5,
         *, data_range: float = 1.0) -> float:
    """Mean structural similarity with a Gaussian window (``window`` taps, ``sigma``), constants
    K1 = 0.01, K2 = 0.03, computed per channel and averaged over channels and images.

    Padding: 'valid' — the map covers only pixels whose window lies inside the image, the same
    region scikit-image's ``structural_similarity(gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False)`` averages. Identical images give 1.0; constant images stay finite.
    With ``mask`` the map is averaged with the mask (at each window's centre) as weight; a mask with
    no weight there raises ``EmptyRegionError`` (use ``masked_ssim`` for a None instead).
    """
    smap = _ssim_mean_map(x, y, window, sigma, data_range)
    if mask is None:
        return float(smap.mean())
    inside, _ = _region_means(smap, _centre_weights(mask, x, window))
    if inside is None:
        raise EmptyRegionError(f"mask has no weight at the {smap.shape[-2]}×{smap.shape[-1]} SSIM window centres "
                               f"(borders of {window // 2} px are outside every full window)")
    return inside


def masked_ssim(x: Tensor, y: Tensor, mask: Tensor, window: int = 11, sigma: float = 1.5,
                *, data_range: float = 1.0) -> tuple[float | None, float | None]:
    """Mean of the SSIM map (see ``ssim``) inside and outside ``mask``, weighted by mask / 1 − mask at
    each window's centre. ``None`` for a region with no weight among the valid window centres."""
    smap = _ssim_mean_map(x, y, window, sigma, data_range)
    return _region_means(smap, _centre_weights(mask, x, window))


# -- silhouettes ---------------------------------------------------------------------------------


def mask_iou(a: Tensor, b: Tensor) -> float:
    """Intersection over union of two silhouettes (or batches of them) thresholded at > 0.5.

    1.0 when both are empty: there is nothing to disagree on (the same rule as ``ops.stages.qa.mask_iou``).
    """
    ma, mb = _mask_2d(a, "a") > 0.5, _mask_2d(b, "b") > 0.5
    if ma.shape[-2:] != mb.shape[-2:] or (ma.shape[0] != mb.shape[0] and 1 not in (ma.shape[0], mb.shape[0])):
        raise MetricInputError(f"a and b differ in shape: {tuple(a.shape)} vs {tuple(b.shape)}")
    union = int((ma | mb).sum())
    return 1.0 if union == 0 else int((ma & mb).sum()) / union


# -- frequency content ---------------------------------------------------------------------------

# Rec. 709 luma weights: the spectrum of perceived brightness, not of each channel separately.
_LUMA = torch.tensor([0.2126, 0.7152, 0.0722], dtype=torch.float64)
# A reference whose HF share is below this has no texture to lose; a ratio against it is meaningless.
_FLAT_HF_SHARE = 1e-9


def _luma(images: Tensor) -> Tensor:
    return torch.einsum("c,nchw->nhw", _LUMA, images)


def _fill_outside(lum: Tensor, weight: Tensor) -> Tensor | None:
    """Blend the background to the region's mean luminance; None for an empty region.

    The silhouette against the background would otherwise be the strongest edge in the image and
    swamp the texture's spectrum; filling with the masked mean leaves only the object's own contrast."""
    total = float(weight.sum())
    if total <= 0.0:
        return None
    mean = float((lum * weight).sum()) / total
    return weight * lum + (1.0 - weight) * mean


def _hf_share(lum: Tensor, weight: Tensor | None, cutoff: float) -> float | None:
    if weight is not None:
        filled = _fill_outside(lum, weight)
        if filled is None:
            return None
        lum = filled
    return high_frequency_ratio(lum, cutoff)


def hf_ratio(views: Tensor, reference: Tensor, cutoff: float = 0.5, mask: Tensor | None = None,
             reference_mask: Tensor | None = None) -> float | None:
    """High-frequency energy of rendered views relative to the reference photo.

    For every image: luminance (Rec. 709 weights of the sRGB values); with masks, the background
    blended to the object's mean luminance; then its HF share = the fraction of mean-removed spectral
    energy at radius ≥ ``cutoff``·Nyquist (``frequency.high_frequency_ratio``). The result is the mean
    share over the views divided by the reference's share: 1 for views as detailed as the photo, < 1
    for blurrier ones (the paper's 3D-prior-only novel views), > 1 for noisier ones.

    ``mask`` (for the views) and ``reference_mask`` must be given together; views whose mask is empty
    are left out of the mean. Returns ``None`` when the reference is flat (HF share < 1e-9: nothing to
    lose), its mask is empty, or every view's mask is empty. Views and reference must share H×W, since
    the cutoff is a fraction of each image's own Nyquist frequency.
    """
    if (mask is None) != (reference_mask is None):
        raise MetricInputError("hf_ratio needs both mask and reference_mask, or neither")
    vs = checked_images(views, "views", colour=True)
    ref = checked_images(reference, "reference", colour=True)
    if ref.shape[0] != 1:
        raise MetricInputError(f"reference must be a single image, got a batch of {ref.shape[0]}")
    n, _, h, w = vs.shape
    if tuple(ref.shape[-2:]) != (h, w):
        raise MetricInputError(f"views are {h}×{w} but the reference is {ref.shape[-2]}×{ref.shape[-1]}")
    if not 0.0 < cutoff < 1.0:
        raise MetricInputError(f"cutoff must lie in (0, 1), got {cutoff}")
    view_w = checked_masks(mask, "mask", n, h, w)[:, 0] if mask is not None else None
    ref_w = checked_masks(reference_mask, "reference_mask", 1, h, w)[:, 0] if reference_mask is not None else None

    ref_share = _hf_share(_luma(ref)[0], None if ref_w is None else ref_w[0], cutoff)
    if ref_share is None or ref_share < _FLAT_HF_SHARE:
        return None
    lum = _luma(vs)
    shares = [_hf_share(lum[i], None if view_w is None else view_w[i], cutoff) for i in range(n)]
    measured = [s for s in shares if s is not None]
    if not measured:
        return None
    return (sum(measured) / len(measured)) / ref_share
