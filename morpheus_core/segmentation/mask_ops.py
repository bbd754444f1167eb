"""Object masks from product photos on near-uniform backgrounds, and mask clean-up maths.

Classical chain: model the background from the image border in CIE Lab; seed the object from
two cues: the colour distance to that background (with shadows down-weighted), and regions
that step edges outline against it at a contrast set from the backdrop's own noise
(``mask_edges``: a white product on a white sweep); clean the seed up (morphology, holes, every
plausible part: ``mask_parts``) and refine it with GrabCut. Arrays are numpy: images H×W×3 float
in [0, 1], masks H×W bool.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from morpheus_core.color import rgb_to_lab
from morpheus_core.segmentation.mask_edges import EdgeCue, EdgeParams, edge_cue
from morpheus_core.segmentation.mask_parts import PartRecord, PartRules, select_parts


@dataclass(frozen=True)
class ClassicalParams:
    """Knobs of the classical chain; the defaults are tuned on studio-style product photos."""

    border_fraction: float = 0.02
    """Width of the border ring that samples the background, as a share of the shorter side (≥ 2 px)."""
    distance_threshold: float = 12.0
    """ΔE from the background above which a pixel starts as object (studio noise is ΔE ≈ 1–3)."""
    shadow_lightness_weight: float = 0.35
    """Weight of darker-than-background lightness in ΔE: shadows darken without a hue change, so they stay out."""
    shadow_tolerance: float = 6.0
    """Seed pixels within this ΔE of a dimmed background colour start as background, for GrabCut to decide."""
    morph_fraction: float = 0.006
    """Opening radius (closing: twice it) as a share of the image diagonal; also GrabCut's undecided band."""
    grabcut_iterations: int = 4
    """GrabCut iterations refining the seed mask; 0 keeps the seed."""
    grabcut_min_iou: float = 0.7
    """Keep the seed when GrabCut's mask overlaps it by less IoU: GrabCut may wander off on low-contrast photos."""
    edges: EdgeParams = field(default_factory=EdgeParams)
    parts: PartRules = field(default_factory=PartRules)
    max_colour_overlap: float = 0.5
    """An edge-outlined region joins the seed when the colour seed covers less than this share of it."""


@dataclass(frozen=True)
class ClassicalResult:
    mask: np.ndarray
    seed_mask: np.ndarray
    background_spread: float  # 90th percentile ΔE of the border around the fitted background
    threshold: float
    grabcut_used: bool
    colour_seed: np.ndarray  # what the colour cue alone found (cleaned)
    edges: EdgeCue
    parts: tuple[PartRecord, ...]  # every component of the final mask, kept or dropped, with why
    cue_pixels: np.ndarray  # pixels either cue marked before morphology (the mask's fill evidence)


def to_lab(rgb: np.ndarray) -> np.ndarray:
    """H×W×3 sRGB floats to H×W×3 Lab (through ``morpheus_core.color``)."""
    t = torch.from_numpy(np.ascontiguousarray(rgb, dtype=np.float32)).permute(2, 0, 1)
    return rgb_to_lab(t).permute(1, 2, 0).numpy()


def border_ring(shape: tuple[int, int], fraction: float) -> np.ndarray:
    h, w = shape
    k = max(2, round(fraction * min(h, w)))
    ring = np.zeros((h, w), dtype=bool)
    ring[:k], ring[-k:], ring[:, :k], ring[:, -k:] = True, True, True, True
    return ring


def _design(xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    return np.stack([np.ones_like(xs), xs, ys, xs * xs, xs * ys, ys * ys], axis=-1)


def fit_background(lab: np.ndarray, fraction: float) -> tuple[np.ndarray, float]:
    """A smooth (quadratic in x, y) Lab background fitted robustly to the border ring.

    A constant background gives its median border colour; studio fall-off, grey sweeps and
    gradients are smooth, so a quadratic captures them. Border pixels far from the first fit
    (the object touching the edge, a stray prop) are dropped before refitting. Returns the
    background image and the 90th-percentile ΔE of border pixels around it (uniformity).
    """
    h, w = lab.shape[:2]
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    xs, ys = 2 * xs / max(w - 1, 1) - 1, 2 * ys / max(h - 1, 1) - 1
    ring = border_ring((h, w), fraction)
    samples = lab[ring].astype(np.float64)
    design = _design(xs[ring], ys[ring])
    resid = np.linalg.norm(samples - np.median(samples, axis=0), axis=1)
    for _ in range(3):
        keep = resid <= max(3.0 * 1.4826 * np.median(resid), 2.0)
        coef, *_ = np.linalg.lstsq(design[keep], samples[keep], rcond=None)
        resid = np.linalg.norm(samples - design @ coef, axis=1)
    background = (_design(xs, ys) @ coef).astype(np.float32)
    return background, float(np.percentile(resid, 90))


def background_distance(lab: np.ndarray, background: np.ndarray, shadow_weight: float) -> np.ndarray:
    """ΔE to the background with darker-than-background lightness down-weighted (shadows)."""
    diff = lab - background
    dl = np.where(diff[..., 0] < 0, shadow_weight * diff[..., 0], diff[..., 0])
    return np.sqrt(dl**2 + diff[..., 1] ** 2 + diff[..., 2] ** 2)


def _disk(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def fill_holes(mask: np.ndarray, background: np.ndarray | None = None, min_open_fraction: float = 0.05) -> np.ndarray:
    """Fill regions not connected to the image border (labels, print, reflections).

    With ``background`` (pixels matching the background colour), a hole that is mostly such
    pixels and at least ``min_open_fraction`` of the object's area stays open: a mug handle.
    Smaller background-coloured holes are white print far more often than see-through gaps.
    """
    _, labels = cv2.connectedComponents((~mask).astype(np.uint8), connectivity=4)
    edge = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    filled = ~np.isin(labels, edge[edge > 0])
    if background is None:
        return filled
    holes = filled & ~mask
    n, hole_labels, stats, _ = cv2.connectedComponentsWithStats(holes.astype(np.uint8), connectivity=4)
    area = max(int(filled.sum()), 1)
    for i in range(1, n):
        if stats[i, cv2.CC_STAT_AREA] >= min_open_fraction * area:
            region = hole_labels == i
            if background[region].mean() >= 0.9:
                filled &= ~region
    return filled


def close_and_open(mask: np.ndarray, radius: int) -> np.ndarray:
    """Close (bridge printed marks and hairline gaps), then open (drop specks). Closing first
    matters: fine print on a light label is a scatter of marks that opening alone would erase,
    splitting the product in two."""
    m = mask.astype(np.uint8)
    if radius > 0:
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, _disk(2 * radius))
        m = cv2.morphologyEx(m, cv2.MORPH_OPEN, _disk(radius))
    return m.astype(bool)


def shadow_like(lab: np.ndarray, background: np.ndarray, tolerance: float) -> np.ndarray:
    """Pixels that look like the background under less light.

    Dimming by k in linear RGB scales XYZ by k, so (L+16, a, b) scales by k^(1/3): a shadow lies
    on the ray from the origin through the background's (L+16, a, b), closer to the origin. The
    test is the distance from that ray (ΔE units) and a scale below 1.
    """
    v = lab + np.array([16.0, 0.0, 0.0], dtype=lab.dtype)
    ref = background + np.array([16.0, 0.0, 0.0], dtype=lab.dtype)
    scale = (v * ref).sum(-1) / np.maximum((ref * ref).sum(-1), 1e-6)
    off_ray = np.linalg.norm(v - scale[..., None] * ref, axis=-1)
    return (scale < 1.0) & (off_ray < tolerance)


def grabcut_refine(rgb: np.ndarray, seed: np.ndarray, certain_bg: np.ndarray, doubtful: np.ndarray,
                   iterations: int, band: int) -> np.ndarray:
    """GrabCut from a seed mask: its core (eroded by ``band``) is sure object, ``certain_bg`` sure
    background, everything else undecided, with ``doubtful`` (shadow-like) seed pixels starting
    as background. Shaded object edges that the seed missed can so still join the object."""
    gc = np.where(certain_bg, cv2.GC_BGD, cv2.GC_PR_BGD).astype(np.uint8)
    core = cv2.erode(seed.astype(np.uint8), _disk(band)).astype(bool) & ~doubtful
    gc[seed & ~doubtful] = cv2.GC_PR_FGD
    gc[core] = cv2.GC_FGD
    if not core.any() or not (gc == cv2.GC_BGD).any():
        return seed.copy()  # nothing certain on one side: GrabCut's colour models would be empty
    bgr = cv2.cvtColor((np.clip(rgb, 0, 1) * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR)
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.setRNGSeed(0)  # GrabCut's GMM initialisation draws random numbers: keep results reproducible
    cv2.grabCut(bgr, gc, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
    return (gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


def _add_outlined(colour_seed: np.ndarray, outlined: np.ndarray, max_overlap: float) -> np.ndarray:
    """The colour seed plus every outlined region it mostly misses (the colour cue is weaker there)."""
    n, labels = cv2.connectedComponents(outlined.astype(np.uint8), connectivity=8)
    seed = colour_seed.copy()
    for i in range(1, n):
        region = labels == i
        if colour_seed[region].mean() < max_overlap:
            seed |= region
    return seed


def classical_segment(rgb: np.ndarray, params: ClassicalParams | None = None) -> ClassicalResult:
    """Segment the product from a near-uniform background (see the module docstring)."""
    p = params or ClassicalParams()
    lab = to_lab(rgb)
    background, spread = fit_background(lab, p.border_fraction)
    dist = background_distance(lab, background, p.shadow_lightness_weight)
    radius = max(1, round(p.morph_fraction * float(np.hypot(*rgb.shape[:2]))))
    # "Certainly background" uses the plain ΔE: shading-darkened object edges must stay undecided.
    certain_bg = np.linalg.norm(lab - background, axis=-1) < 0.5 * p.distance_threshold
    colour_seed = fill_holes(close_and_open(dist > p.distance_threshold, radius), certain_bg)
    cue = edge_cue(lab, background, border_ring(rgb.shape[:2], p.border_fraction), p.edges)
    # Outlined regions are product even where their colour matches a dimmed backdrop.
    shadow = shadow_like(lab, background, p.shadow_tolerance) & ~cue.regions
    certain_bg &= ~cue.regions
    seed = _add_outlined(colour_seed, cue.regions, p.max_colour_overlap)
    cue_pixels = (dist > p.distance_threshold) | cue.regions
    seed, parts = select_parts(fill_holes(seed, certain_bg), p.parts, shadow)
    if not seed.any():
        return ClassicalResult(seed, seed, spread, p.distance_threshold, False, colour_seed, cue, parts, cue_pixels)
    refined = grabcut_refine(rgb, seed, certain_bg, shadow, p.grabcut_iterations, 2 * radius)
    refined, refined_parts = select_parts(fill_holes(close_and_open(refined, radius), certain_bg), p.parts, shadow)
    use = p.grabcut_iterations > 0 and iou(refined, seed) >= p.grabcut_min_iou
    return ClassicalResult(refined if use else seed, seed, spread, p.distance_threshold, use, colour_seed, cue,
                           refined_parts if use else parts, cue_pixels)
