"""Which connected parts of a mask are the product: all plausible parts, not only the largest.

A pair of shoes, earrings or headphones whose ear cups do not touch the band are several
components in the photo. A part is kept unless it is much smaller than the largest one (a speck,
a crumb), touches the image border while the largest does not (a prop, the edge of a sweep), or
looks like backdrop in shadow. Every part is recorded with the reason it was kept or dropped.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class PartRules:
    min_relative_area: float = 0.08
    """Parts smaller than this share of the largest part's area are dropped as specks or crumbs."""
    max_shadow_share: float = 0.6
    """A part with a larger share of shadow-like (dimmed backdrop) pixels is dropped as a shadow."""


@dataclass(frozen=True)
class PartRecord:
    """One connected component of the mask; ``bbox`` (x0, y0, x1, y1) in the mask's pixels."""

    bbox: tuple[int, int, int, int]
    area_fraction: float  # of the image
    relative_area: float  # of the largest part
    kept: bool
    reason: str


def scale_box(box: tuple[int, int, int, int], sx: float, sy: float) -> tuple[int, int, int, int]:
    """An (x0, y0, x1, y1) box in pixels of an image scaled by (sx, sy)."""
    return round(box[0] * sx), round(box[1] * sy), round(box[2] * sx), round(box[3] * sy)


def scaled_parts(parts: tuple[PartRecord, ...], sx: float, sy: float) -> tuple[PartRecord, ...]:
    return tuple(dataclasses.replace(r, bbox=scale_box(r.bbox, sx, sy)) for r in parts)


def kept_count(parts: tuple[PartRecord, ...]) -> int:
    return sum(r.kept for r in parts)


def _touches_border(stats: np.ndarray, shape: tuple[int, int]) -> bool:
    x, y, w, h = (int(v) for v in stats[:4])
    return x == 0 or y == 0 or x + w == shape[1] or y + h == shape[0]


def select_parts(mask: np.ndarray, rules: PartRules | None = None,
                 shadow: np.ndarray | None = None) -> tuple[np.ndarray, tuple[PartRecord, ...]]:
    """(the kept parts' union, one record per component, largest first). ``shadow``: H×W bool of
    pixels that look like backdrop in shadow (None: that rule is not applied)."""
    r = rules or PartRules()
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros(mask.shape, bool), ()
    order = 1 + np.argsort(-stats[1:, cv2.CC_STAT_AREA], kind="stable")
    largest = float(stats[order[0], cv2.CC_STAT_AREA])
    largest_at_border = _touches_border(stats[order[0]], mask.shape)
    keep = np.zeros(n, bool)
    records = []
    for rank, i in enumerate(order):
        area = float(stats[i, cv2.CC_STAT_AREA])
        relative = area / largest
        shadow_share = float(shadow[labels == i].mean()) if shadow is not None else 0.0
        if rank == 0:
            kept, reason = True, "the largest part"
        elif relative < r.min_relative_area:
            kept, reason = False, f"dropped: {relative:.1%} of the largest part (minimum {r.min_relative_area:.0%})"
        elif _touches_border(stats[i], mask.shape) and not largest_at_border:
            kept, reason = False, "dropped: touches the image border (a prop or the backdrop's edge)"
        elif shadow_share > r.max_shadow_share:
            kept, reason = False, f"dropped: {shadow_share:.0%} of it looks like backdrop in shadow"
        else:
            kept, reason = True, f"kept: {relative:.0%} of the largest part"
        keep[i] = kept
        x, y, w, h = (int(v) for v in stats[i, :4])
        records.append(PartRecord((x, y, x + w, y + h), round(area / mask.size, 5), round(relative, 4), kept, reason))
    return keep[labels], tuple(records)
