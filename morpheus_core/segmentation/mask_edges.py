"""The edge cue of the classical chain: regions a sharp outline separates from the backdrop.

Colour distance cannot tell a white product on a white sweep from its own shadow: both are the
backdrop's colour, darker. What differs is the transition: a product's outline is a step, a
shadow fades in over many pixels. So step edges are found (Canny with hysteresis on the
dominant Lab channel, keeping only edges much sharper at a fine scale than at a coarse one, which
a ramp is not), and the backdrop is flooded from the image border through the space between them.
Where a shadow as dark as the product hides part of its outline, the outline has a gap: the
flood runs through free space eroded by ``gap_radius`` and is grown back, so gaps narrower than
twice that radius do not leak. The thresholds come from the backdrop's own gradient noise
(measured on the border ring), so the cue adapts to each photo instead of a fixed contrast.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class EdgeParams:
    smoothing: float = 0.8
    """Gaussian σ (px) before the fine-scale gradient."""
    coarse_smoothing: float = 2.5
    """σ (px) of the coarse-scale gradient that tells steps from ramps."""
    min_sharpness: float = 1.6
    """Least fine/coarse gradient ratio of a step edge (a step's is ≈ coarse/fine σ, a ramp's ≈ 1)."""
    high_factor: float = 1.6
    """Canny's high hysteresis threshold, as a multiple of the backdrop's 99th-percentile gradient (noise)."""
    low_factor: float = 0.8
    """Canny's low hysteresis threshold, as a multiple of the backdrop's 99th-percentile gradient (noise)."""
    min_gradient: float = 0.3
    """Floor (ΔE per px) of the high threshold (half of it: the low one): a noiseless render still needs a step."""
    gap_radii: tuple[int, ...] = (3, 6, 9, 12, 16)
    """Erosion radii (px) tried in turn: shadows joined through outline gaps < 2·radius are cut off."""
    # Contrast to the backdrop that a region needs, as a multiple of the backdrop's own 90th-percentile
    # ΔE after smoothing (its noise and unmodelled shading), within [min_contrast, max_contrast].
    contrast_smoothing: float = 1.5
    """σ (px) of the Lab image whose distance to the backdrop is measured for the contrast test."""
    contrast_factor: float = 2.5
    """Contrast (ΔE) a region needs, as a multiple of the backdrop's 90th-percentile smoothed ΔE (noise, shading)."""
    min_contrast: float = 2.0
    """Floor (ΔE) of the contrast a region needs to the backdrop."""
    max_contrast: float = 12.0
    """Cap (ΔE) of the contrast a region needs to the backdrop (a noisy backdrop asks no more than this)."""
    min_outline_support: float = 0.8
    """Share of a region's outline that must lie on step edges; failing pieces retry at the next gap radius."""


@dataclass(frozen=True)
class EdgeCue:
    edges: np.ndarray  # H×W bool: step-edge pixels
    regions: np.ndarray  # H×W bool: regions apart from the backdrop whose outline is mostly step edges
    noise: float  # the backdrop's 99th-percentile fine-scale gradient (ΔE per pixel)
    contrast_threshold: float  # ΔE a region needed to stand apart from the backdrop


def _gradients(lab: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(dx, dy, |∇|) of the smoothed Lab image on its dominant channel per pixel, ΔE per pixel."""
    smooth = cv2.GaussianBlur(lab, (0, 0), sigma) if sigma > 0 else lab
    gx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    power = gx**2 + gy**2
    k = power.argmax(axis=-1)[..., None]
    dx, dy = np.take_along_axis(gx, k, -1)[..., 0], np.take_along_axis(gy, k, -1)[..., 0]
    return dx, dy, np.sqrt(np.take_along_axis(power, k, -1)[..., 0])


def step_edges(lab: np.ndarray, ring: np.ndarray, p: EdgeParams) -> tuple[np.ndarray, float]:
    dx, dy, grad = _gradients(lab, p.smoothing)
    coarse = _gradients(lab, p.coarse_smoothing)[2]
    ring_grad = grad[ring]
    # The border can hold a stray prop or a seam: the median-based cut keeps them out of the noise.
    noise = float(np.percentile(ring_grad[ring_grad <= 4 * np.median(ring_grad) + 1e-6], 99))
    sharp = grad >= p.min_sharpness * coarse
    dx, dy = np.where(sharp, dx, 0.0), np.where(sharp, dy, 0.0)
    scale = 64.0  # Canny takes 16-bit gradients: keep 1/64 ΔE of precision
    high = max(p.high_factor * noise, p.min_gradient) * scale
    low = min(max(p.low_factor * noise, 0.5 * p.min_gradient) * scale, high)
    edges = cv2.Canny(np.round(dx * scale).astype(np.int16), np.round(dy * scale).astype(np.int16),
                      low, high, L2gradient=True) > 0
    return edges, noise


def _disk(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1,) * 2)


def near_edges(edges: np.ndarray, tolerance: int = 2) -> np.ndarray:
    """Pixels within ``tolerance`` px of a step edge."""
    return cv2.dilate(edges.astype(np.uint8), _disk(tolerance)).astype(bool)


def outline_share(region: np.ndarray, near: np.ndarray, ignore: np.ndarray | None = None) -> float:
    """Share of ``region``'s outline pixels inside ``near``; outline pixels in ``ignore`` do not
    count (0 when no outline pixel is left)."""
    outline = region & ~cv2.erode(region.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    if ignore is not None:
        outline &= ~ignore
    return float(near[outline].mean()) if outline.any() else 0.0


def outline_support(region: np.ndarray, edges: np.ndarray, tolerance: int = 2) -> float:
    """Share of ``region``'s outline pixels within ``tolerance`` px of a step edge."""
    return outline_share(region, near_edges(edges, tolerance))


def _outlined_pieces(apart: np.ndarray, band: np.ndarray, near: np.ndarray, radius: int, min_support: float,
                     accepted: np.ndarray) -> np.ndarray:
    """``accepted`` grown by the pieces of ``apart`` cut at ``radius`` whose outline lies on edges.

    Eroding cuts the necks through which a shadow joins the product where its outline is hidden;
    growing back step by step inside ``apart`` never crosses an outline. A shadow beside the product
    shares the product's edge and has none of its own, so outline next to an accepted region does
    not count as support.
    """
    core = cv2.erode(apart.astype(np.uint8), _disk(radius))
    n, labels = cv2.connectedComponents(core, connectivity=8)
    labels = labels.astype(np.float32)
    for _ in range(radius + 1):
        labels = np.where(apart & (labels == 0), cv2.dilate(labels, np.ones((3, 3), np.uint8)), labels)
    grow = np.ones((5, 5), np.uint8)
    regions = []
    for i in range(1, n):
        piece = labels == i
        # The outline itself (the edge band around the piece) belongs to the product.
        regions.append(piece | (cv2.dilate(piece.astype(np.uint8), grow).astype(bool) & band))
    regions.sort(key=lambda r: -outline_share(r, near))
    accepted = accepted.copy()
    for region in regions:
        beside = cv2.dilate(accepted.astype(np.uint8), _disk(3)).astype(bool)
        if outline_share(region, near, beside) >= min_support:
            accepted |= region
    return accepted


def edge_cue(lab: np.ndarray, background: np.ndarray, ring: np.ndarray, params: EdgeParams | None = None) -> EdgeCue:
    """Regions that differ from the backdrop and that step edges outline (see the module docstring).

    ``background``: the fitted backdrop in Lab; ``ring`` samples the backdrop.
    """
    p = params or EdgeParams()
    edges, noise = step_edges(lab, ring, p)
    # Smoothing before the distance, not after: the norm of noise does not average out.
    smooth = np.linalg.norm(cv2.GaussianBlur(lab, (0, 0), p.contrast_smoothing) - background, axis=-1)
    spread = float(np.percentile(smooth[ring], 90))
    threshold = min(max(p.contrast_factor * spread, p.min_contrast), p.max_contrast)
    band = cv2.dilate(edges.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    apart = (smooth > threshold) & ~band
    regions = np.zeros(smooth.shape, bool)
    near = near_edges(edges)
    for radius in p.gap_radii:
        regions = _outlined_pieces(apart & ~regions, band, near, radius, p.min_outline_support, regions)
    return EdgeCue(edges, regions, noise, threshold)
