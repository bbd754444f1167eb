"""Colour deviation (weight-free QA): how far the colour distribution of rendered views drifts from the
reference photo's, from their a*b* histograms inside the masks.

Image and mask conventions, input checking and the ``None`` for empty regions are those of
``morpheus_core.metrics.image``, whose argument checks this module shares.
"""

from __future__ import annotations

import torch
from torch import Tensor

from morpheus_core.color import rgb_to_lab
from morpheus_core.metrics.image import MetricInputError, checked_images, checked_masks

# a*, b* of sRGB colours lie within about [−108, 99]; the usual 8-bit Lab range holds them all.
_AB_RANGE = (-128.0, 128.0)


def _ab_histogram(rgb: Tensor, weight: Tensor, bins: int) -> Tensor | None:
    """Normalised bins×bins a*b* histogram of one image (3, H, W) weighted by ``weight`` (H, W).

    Soft (bilinear) binning: each pixel splits its weight between the two nearest bin centres per
    axis, so the distance changes smoothly with colour instead of jumping at bin borders."""
    total = float(weight.sum())
    if total <= 0.0:
        return None
    lab = rgb_to_lab(rgb).double()
    keep = weight > 0
    wts = weight[keep]
    lo, hi = _AB_RANGE
    width = (hi - lo) / bins
    hist = torch.zeros(bins * bins, dtype=torch.float64)
    coords = []
    for ch in (1, 2):
        t = ((lab[ch][keep] - lo) / width - 0.5).clamp(0.0, bins - 1.0)
        i0 = t.floor().long().clamp(max=bins - 1)
        frac = t - i0
        coords.append(((i0, 1.0 - frac), ((i0 + 1).clamp(max=bins - 1), frac)))
    for ia, wa in coords[0]:
        for ib, wb in coords[1]:
            hist.index_add_(0, ia * bins + ib, wts * wa * wb)
    return hist / hist.sum()


def colour_deviation(views: Tensor, view_masks: Tensor, reference: Tensor, reference_mask: Tensor,
                     bins: int = 16) -> float | None:
    """Distance between the colour distribution of the views (e.g. a turntable) and the reference,
    inside the masks: 1 − Bhattacharyya coefficient of normalised a*b* histograms (CIE Lab, D65).

    Histograms: ``bins``×``bins`` over a*, b* ∈ [−128, 128] with bilinear soft binning, pixels weighted
    by their mask value. L* is left out on purpose: novel views are shaded differently from the photo,
    while the paper's low-frequency drift is a change of hue and saturation. The views' histograms
    are normalised one by one and averaged, so every view counts equally whatever its silhouette size.

    The value lies in [0, 1]: 0 for identical distributions, 1 for disjoint ones. ``None`` when the
    reference mask is empty or every view mask is empty (views with empty masks are left out).
    The views may have a different resolution than the reference.
    """
    if not isinstance(bins, int) or bins < 2:
        raise MetricInputError(f"bins must be an integer ≥ 2, got {bins!r}")
    vs = checked_images(views, "views", colour=True)
    ref = checked_images(reference, "reference", colour=True)
    if ref.shape[0] != 1:
        raise MetricInputError(f"reference must be a single image, got a batch of {ref.shape[0]}")
    n, _, h, w = vs.shape
    vm = checked_masks(view_masks, "view_masks", n, h, w)
    rm = checked_masks(reference_mask, "reference_mask", 1, ref.shape[-2], ref.shape[-1])
    ref_hist = _ab_histogram(ref[0], rm[0, 0], bins)
    if ref_hist is None:
        return None
    view_hists = [hst for i in range(n) if (hst := _ab_histogram(vs[i], vm[i, 0], bins)) is not None]
    if not view_hists:
        return None
    view_hist = torch.stack(view_hists).mean(dim=0)
    bc = float(torch.sqrt(view_hist * ref_hist).sum())
    # Rounding can push the coefficient a hair above 1 for identical histograms.
    return min(1.0, max(0.0, 1.0 - bc))
