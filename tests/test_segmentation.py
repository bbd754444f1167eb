"""The classical chain on generated product photos with known masks, and its building blocks."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from morpheus_core.segmentation.mask_ops import (
    classical_segment,
    fill_holes,
    fit_background,
    iou,
    shadow_like,
    to_lab,
)
from morpheus_core.segmentation.mask_parts import select_parts
from tests.photo_factory import product_photo, segmentation_set

SPECS = segmentation_set(seed=11)


@pytest.mark.parametrize("spec", SPECS, ids=lambda s: f"{s.shape}-{s.background}-{s.texture}")
def test_classical_chain_iou(spec) -> None:
    rgb, truth = product_photo(spec)
    result = classical_segment(rgb.astype(np.float32) / 255.0)
    score = iou(result.mask, truth)
    print(f"IoU {spec.shape}/{spec.background}/{spec.texture}: {score:.4f}")
    assert score >= 0.95
    assert result.background_spread < 8.0  # the studio backgrounds count as near-uniform


def test_the_set_covers_every_background_and_has_shadows() -> None:
    assert {s.background for s in SPECS} == {"white", "grey", "gradient"}
    rgb, truth = product_photo(SPECS[0])
    below = rgb[~truth].astype(float).mean(axis=1)
    assert below.min() < 0.8 * np.median(below)  # a shadow darker than the rest of the backdrop


def test_gradient_background_is_fitted() -> None:
    h, w = 60, 80
    ys, xs = np.mgrid[0:h, 0:w] / np.array([h - 1, w - 1])[:, None, None]
    rgb = np.stack([0.9 - 0.3 * ys, 0.85 - 0.2 * xs, 0.8 + 0.0 * xs], axis=-1).astype(np.float32)
    lab = to_lab(rgb)
    background, spread = fit_background(lab, 0.05)
    assert spread < 0.5 and np.abs(background - lab).max() < 2.0  # a plain median would be off by > 10 ΔE


def test_shadow_test_separates_dimmed_background_from_colour() -> None:
    bg = np.array([0.9, 0.8, 0.85], np.float32)
    pixels = np.stack([bg * 0.5, bg * 0.9, np.array([0.2, 0.5, 0.8], np.float32), bg * 1.0])[None]
    lab, ref = to_lab(pixels), to_lab(np.broadcast_to(bg, pixels.shape).copy())
    assert shadow_like(lab, ref, 6.0)[0].tolist() == [True, True, False, False]


def test_fill_holes_keeps_handles_open_and_fills_print() -> None:
    mask = np.zeros((100, 100), bool)
    cv2.circle(mask.view(np.uint8), (50, 50), 40, 1, -1)
    mask[40:60, 40:60] = False  # a big see-through gap (background-coloured)
    mask[20:24, 45:49] = False  # a small white print mark (also background-coloured)
    background = ~mask
    filled = fill_holes(mask, background)
    assert not filled[50, 50] and filled[22, 46]
    assert fill_holes(mask)[50, 50]  # without colour evidence every hole is filled


def test_parts_are_kept_unless_specks_border_props_or_shadows() -> None:
    mask = np.zeros((100, 100), bool)
    mask[20:60, 10:40] = True  # the largest part
    mask[25:55, 55:80] = True  # a second part, 62 % of it: kept
    mask[80:82, 50:52] = True  # a speck: dropped
    mask[0:30, 90:100] = True  # touches the border while the largest does not: dropped
    mask[70:90, 10:30] = True  # a shadow-like part: dropped
    shadow = np.zeros_like(mask)
    shadow[70:90, 10:30] = True
    kept, records = select_parts(mask, shadow=shadow)
    assert kept[40, 20] and kept[40, 60] and not kept[81, 51] and not kept[10, 95] and not kept[80, 20]
    assert [r.kept for r in records] == [True, True, False, False, False]
    reasons = [r.reason for r in records]
    assert reasons[0] == "the largest part" and reasons[1].startswith("kept: 62%")
    assert any("border" in r for r in reasons) and any("shadow" in r for r in reasons)
    assert any("of the largest part (minimum" in r for r in reasons)
    assert records[1].bbox == (55, 25, 80, 55) and records[0].relative_area == 1.0
    empty, none = select_parts(np.zeros((5, 5), bool))
    assert not empty.any() and none == ()
