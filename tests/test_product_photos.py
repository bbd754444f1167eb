"""Product photos as catalogs hold them: white on white, separate parts, and photos that are not
studio shots (the edge cue, every part, mask confidence). Calibration over many more photos:
benchmarks/results/prepare_calibration.md."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from morpheus_core.priors.proxy.shape import InflationConfig, from_reference_folder
from morpheus_core.segmentation.mask_confidence import ConfidenceParams, Ramp, mask_confidence
from morpheus_core.segmentation.mask_edges import edge_cue
from morpheus_core.segmentation.mask_ops import border_ring, classical_segment, fit_background, iou, to_lab
from ops.cli import main
from ops.intake.errors import LowConfidenceError
from ops.intake.plan import plan_reference
from ops.intake.prepare import prepare_reference, read_reference
from ops.intake.segment import SegmentConfig, Segmenter
from tests.photo_factory import SHAPES, multipart_photo, white_on_white_photo

SKIMAGE = pytest.importorskip("skimage.data")
REAL = Path(SKIMAGE.__file__).parent


def _float(rgb: np.ndarray) -> np.ndarray:
    return rgb.astype(np.float32) / 255.0


# Seeds the calibration does not use (it uses 100·ΔE + 10·shape + 1..2).
@pytest.mark.parametrize("delta_e", [6, 8, 12])
def test_white_on_white_is_found_from_delta_e_6(delta_e: int) -> None:
    for i, shape in enumerate(SHAPES):
        rgb, truth = white_on_white_photo(delta_e, 7000 + 10 * delta_e + i, shape)
        result = classical_segment(_float(rgb))
        score = iou(result.mask, truth)
        print(f"ΔE {delta_e} {shape}: IoU {score:.3f}, colour seed {result.colour_seed.mean():.3f}")
        assert score >= 0.9
        assert [p.kept for p in result.parts].count(True) == 1


def test_below_colour_contrast_the_edge_cue_finds_the_object() -> None:
    rgb, truth = white_on_white_photo(6, 7061, "cylinder")
    result = classical_segment(_float(rgb))
    assert iou(result.colour_seed, truth) < 0.1  # the fixed ΔE 12 colour cue alone finds nothing
    assert iou(result.edges.regions, truth) >= 0.85


def test_a_soft_shadow_alone_is_not_outlined() -> None:
    """A dark smudge fading in over many pixels (a shadow, no product) is no outlined region."""
    rng = np.random.default_rng(int(np.random.SeedSequence().entropy % 2**32))
    ys, xs = np.mgrid[0:240, 0:240] / 240.0
    smudge = np.exp(-(((xs - rng.uniform(0.4, 0.6)) / 0.2) ** 2 + ((ys - rng.uniform(0.4, 0.6)) / 0.06) ** 2))
    rgb = np.repeat((0.97 * (1 - 0.3 * smudge))[..., None], 3, -1) + rng.normal(0, 1.5 / 255, (240, 240, 3))
    lab = to_lab(np.clip(rgb, 0, 1).astype(np.float32))
    background, _ = fit_background(lab, 0.02)
    cue = edge_cue(lab, background, border_ring((240, 240), 0.02))
    assert not cue.regions.any()


@pytest.mark.parametrize(("parts", "gap"), [(2, 10), (3, 30), (4, 60), (2, 60)])
def test_every_part_is_kept(parts: int, gap: int) -> None:
    rgb, truths = multipart_photo(parts, gap, 9000 + 10 * parts + gap, ("white", "grey", "gradient")[parts % 3])
    result = classical_segment(_float(rgb))
    union = np.any(np.stack(truths), axis=0)
    kept = [(result.mask & t).sum() / t.sum() for t in truths]
    print(f"{parts} parts, gap {gap}: IoU {iou(result.mask, union):.3f}, kept {np.round(kept, 3)}")
    assert iou(result.mask, union) >= 0.9 and min(kept) >= 0.9


def test_multipart_reference_records_parts_and_feeds_plan_and_proxy(tmp_path: Path) -> None:
    rgb, truths = multipart_photo(3, 40, 9123, "grey", size=384)
    Image.fromarray(rgb).save(tmp_path / "earrings.png")
    info = prepare_reference(tmp_path / "earrings.png", tmp_path / "ref")
    assert info.kept_parts == 3 and all(p.reason for p in info.parts)
    data = json.loads((tmp_path / "ref" / "reference.json").read_text())
    assert [p["kept"] for p in data["parts"]][:3] == [True, True, True]
    assert data["confidence"]["score"] >= 0.5 and set(data["confidence"]["factors"]) >= {"backdrop", "agreement"}
    for record, truth in zip(sorted(info.parts[:3], key=lambda p: p.bbox[0]), truths, strict=True):
        ys, xs = np.nonzero(truth)
        assert np.allclose(record.bbox, (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1), atol=4)
    assert read_reference(tmp_path / "ref") == info
    plan = plan_reference(tmp_path / "ref")
    assert "3 part(s)" in plan.segmentation.reason and plan.segmentation.measurements["parts"] == 3
    proxy = from_reference_folder(tmp_path / "ref", 256, InflationConfig(grid_resolution=48))
    n, _ = cv2.connectedComponents(proxy.mask.cpu().numpy().astype(np.uint8), connectivity=8)
    assert n - 1 == 3  # the proxy shape inflates every part


def test_confidence_is_the_product_of_ramped_factors() -> None:
    rng = np.random.default_rng(int(np.random.SeedSequence().entropy % 2**32))
    mask = np.zeros((200, 200), bool)
    cx, cy, r = rng.uniform(80, 120), rng.uniform(80, 120), rng.uniform(30, 50)
    yy, xx = np.mgrid[0:200, 0:200]
    mask[np.hypot(xx - cx, yy - cy) <= r] = True
    edges = mask ^ cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    good = mask_confidence(mask, 1, backdrop_spread=2.0, edges=edges, cue_pixels=mask)
    assert good.score == 1.0 and set(good.factors) == {"coverage", "border", "compactness", "parts", "backdrop",
                                                       "agreement", "fill"}
    spread = rng.uniform(7, 19)
    weak = mask_confidence(mask, 1, backdrop_spread=spread, edges=edges, cue_pixels=mask)
    assert weak.factors["backdrop"] == pytest.approx((20 - spread) / 14, abs=1e-3)
    assert weak.score == pytest.approx(weak.factors["backdrop"], abs=1e-3)
    sparse = mask_confidence(mask, 30, edges=np.zeros_like(mask), cue_pixels=np.zeros_like(mask))
    assert sparse.score == 0.0 and sparse.weakest()[0].startswith(("agreement 0.00", "fill 0.00", "parts 0.00"))
    assert Ramp(0.0, 1.0)(2.0) == 1.0 and Ramp(1.0, 0.0)(2.0) == 0.0 and Ramp(0.0, 4.0)(1.0) == 0.25
    assert isinstance(ConfidenceParams().backdrop, Ramp)


def test_confidence_thresholds_must_be_ordered() -> None:
    with pytest.raises(ValueError, match="min_confidence"):
        SegmentConfig(min_confidence=0.6, ok_confidence=0.5)


def test_the_three_outcomes(tmp_path: Path) -> None:
    """ok: a studio-style photo; warning: a real photo with a weak cue; failure: a table scene."""
    segmenter = Segmenter(SegmentConfig(use_rembg=False))
    rgb, _ = multipart_photo(2, 30, 9555, "white", size=320)
    Image.fromarray(rgb).save(tmp_path / "pair.png")
    ok = prepare_reference(tmp_path / "pair.png", tmp_path / "ok", segmenter=segmenter)
    assert ok.status == "ok" and ok.confidence["score"] >= 0.5
    warned = prepare_reference(REAL / "clock_motion.png", tmp_path / "warned", segmenter=segmenter)
    assert warned.status == "warning" and any("confidence" in w and "check the mask preview" in w
                                              for w in warned.warnings)
    assert 0.15 <= warned.confidence["score"] < 0.5
    with pytest.raises(LowConfidenceError) as failure:
        prepare_reference(REAL / "coffee.png", tmp_path / "coffee", segmenter=segmenter)
    message = str(failure.value)
    assert "coffee.png" in message and "backdrop" in message and "$U2NET_HOME" in message and "alpha" in message
    assert not (tmp_path / "coffee").exists() and not list(tmp_path.glob(".coffee*"))  # nothing half-written
    # The threshold is a setting: lowered, the same photo passes with a warning.
    lenient = Segmenter(SegmentConfig(use_rembg=False, min_confidence=0.0))
    assert prepare_reference(REAL / "coffee.png", tmp_path / "coffee", segmenter=lenient).status == "warning"


def test_cli_stops_a_low_confidence_photo_with_the_fix(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["prepare", str(REAL / "coffee.png"), "--out", str(tmp_path / "ref"), "--no-rembg", "--strict"])
    out = capsys.readouterr().out
    assert code == 1 and "failed" in out and "LowConfidenceError" in out and "U2NET_HOME" in out
    assert main(["prepare", str(REAL / "coffee.png"), "--out", str(tmp_path / "ref"), "--no-rembg",
                 "--min-confidence", "0"]) == 0
    assert "warning" in capsys.readouterr().out


def test_a_low_confidence_photo_stops_before_the_gpu_stages(tmp_path: Path) -> None:
    from assets_store.store import Store
    from ops.pipeline.runner import Pipeline, stages_until
    from tests.pipeline_helpers import tiny_config

    store = Store(tmp_path / "store")
    cfg = tiny_config("reference.prepare.segment.use_rembg=false")
    out = Pipeline(store, cfg, "tiny").run([(REAL / "coffee.png", "coffee.png")])[0]
    assert out.status == "failed" and out.error.startswith("reference: LowConfidenceError")
    assert "coffee.png" in out.error
    assert [s.stage for s in out.stages] == ["reference"]
    assert all(store.read_manifest("coffee.png", s) is None for s in ("reference", "nerf"))
    # The threshold is a pipeline setting too.
    lenient = tiny_config("reference.prepare.segment.use_rembg=false", "reference.prepare.segment.min_confidence=0.0")
    out = Pipeline(store, lenient, "tiny").run([(REAL / "coffee.png", "coffee.png")], stages_until("reference"))[0]
    ref = store.read_manifest("coffee.png", "reference")
    assert out.error is None and ref is not None and ref.metrics["mask_confidence"] < 0.15
    assert any("confidence" in n for n in ref.notes)
