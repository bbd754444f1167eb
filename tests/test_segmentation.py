"""The classical chain on generated product photos with known masks, and its building blocks."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from morpheus_core.mask_ops import (
    classical_segment,
    fill_holes,
    fit_background,
    iou,
    largest_component,
    shadow_like,
    to_lab,
)
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


def test_largest_component() -> None:
    mask = np.zeros((50, 50), bool)
    mask[5:10, 5:10] = True
    mask[20:40, 20:40] = True
    out = largest_component(mask)
    assert out[30, 30] and not out[7, 7]
    assert not largest_component(np.zeros((5, 5), bool)).any()
