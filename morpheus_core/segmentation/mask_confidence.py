"""How much to trust a product mask: one score from cues that fail on photos that are not studio shots.

Each factor maps one measurement to [0, 1] by a linear ramp between a "bad" and a "good" end;
the score is their product, so one clearly failed cue is enough to stop a photo while several
mildly weak ones only warn. The ramps' ends were calibrated on the generated studio, white-on-
white and multi-part photos against real cluttered photographs
(``benchmarks/results/prepare_calibration.md``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from morpheus_core.segmentation.mask_edges import outline_support


@dataclass(frozen=True)
class Ramp:
    bad: float
    """Measurement at which this confidence factor is 0 (and beyond, away from ``good``)."""
    good: float
    """Measurement at which this confidence factor is 1 (and beyond); the factors multiply into the score."""

    def __call__(self, value: float) -> float:
        return float(np.clip((value - self.bad) / (self.good - self.bad), 0.0, 1.0))


@dataclass(frozen=True)
class ConfidenceParams:
    backdrop: Ramp = Ramp(20.0, 6.0)
    """Border ΔE spread around the fitted backdrop (a studio sweep: 0.5–3; a room: 20+); classical masks only."""
    coverage_low: Ramp = Ramp(0.005, 0.05)
    """Share of the image the mask covers, low end: tiny masks are specks."""
    coverage_high: Ramp = Ramp(0.95, 0.6)
    """Share of the image the mask covers, high end: huge masks are the whole scene."""
    border: Ramp = Ramp(0.25, 0.02)
    """Share of the image's border pixels the mask covers (a product sits inside the frame)."""
    compactness: Ramp = Ramp(0.3, 0.6)
    """Area-weighted solidity of the kept parts (area / convex hull area; a horse silhouette: 0.55)."""
    agreement: Ramp = Ramp(0.2, 0.7)
    """Share of the mask's outline on step edges: where colour and edge cues agree; classical masks only."""
    fill: Ramp = Ramp(0.4, 0.8)
    """Share of the mask a cue marked before morphology filled it (text and clutter: sparse); classical only."""
    parts: Ramp = Ramp(16.0, 6.0)
    """Separate parts kept: a set of 2–6 is a product, dozens a texture or a crowd."""


@dataclass(frozen=True)
class MaskConfidence:
    score: float
    factors: dict[str, float]  # each factor in [0, 1]
    measurements: dict[str, float]  # what each factor was computed from

    def weakest(self, n: int = 3) -> list[str]:
        """The ``n`` lowest factors below 1, as 'name 0.42 (measurement)'."""
        low = sorted((v, k) for k, v in self.factors.items() if v < 1.0)[:n]
        return [f"{k} {v:.2f} (measured {self.measurements[k]:.3g})" for v, k in low]


def solidity(mask: np.ndarray) -> float:
    """Area-weighted mean of each part's area over its convex hull's area (1 for no parts)."""
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    total = weighted = 0.0
    for i in range(1, n):
        area = float(stats[i, cv2.CC_STAT_AREA])
        hull = cv2.contourArea(cv2.convexHull(cv2.findNonZero((labels == i).astype(np.uint8))))
        weighted += area * min(1.0, area / max(hull, 1.0))
        total += area
    return weighted / total if total else 1.0


def border_share(mask: np.ndarray) -> float:
    return float(np.concatenate([mask[0], mask[-1], mask[:, 0], mask[:, -1]]).mean())


def mask_confidence(mask: np.ndarray, parts: int, params: ConfidenceParams | None = None, *,
                    backdrop_spread: float | None = None, edges: np.ndarray | None = None,
                    cue_pixels: np.ndarray | None = None) -> MaskConfidence:
    """The confidence of ``mask`` (H×W bool, ``parts`` kept components). The classical chain passes
    its backdrop spread, step edges and raw cue pixels; a learned mask (rembg) has none of them,
    and those factors are left out."""
    p = params or ConfidenceParams()
    area = float(mask.mean())
    m = {"coverage": round(area, 4), "border": round(border_share(mask), 4),
         "compactness": round(solidity(mask), 3), "parts": float(parts)}
    f = {"coverage": min(p.coverage_low(area), p.coverage_high(area)), "border": p.border(m["border"]),
         "compactness": p.compactness(m["compactness"]), "parts": p.parts(parts)}
    if backdrop_spread is not None:
        m["backdrop"] = round(backdrop_spread, 2)
        f["backdrop"] = p.backdrop(backdrop_spread)
    if edges is not None:
        m["agreement"] = round(outline_support(mask, edges), 3)
        f["agreement"] = p.agreement(m["agreement"])
    if cue_pixels is not None:
        m["fill"] = round(float(cue_pixels[mask].mean()) if mask.any() else 0.0, 3)
        f["fill"] = p.fill(m["fill"])
    f = {k: round(v, 3) for k, v in f.items()}
    return MaskConfidence(round(float(np.prod(list(f.values()))), 3), f, m)
