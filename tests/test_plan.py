"""The per-scene plan: refinement skipped for flat objects, kept for detail; grid and reasons in JSON."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from ops.intake.plan import PLAN_FILE, PlanConfig, StagePlan, make_plan, plan_reference, read_plan
from ops.intake.prepare import prepare_reference, read_reference
from tests.photo_factory import PhotoSpec, product_photo


def _prepared(tmp_path: Path, spec: PhotoSpec, name: str) -> Path:
    rgb, _ = product_photo(spec)
    photo = tmp_path / f"{name}.png"
    Image.fromarray(rgb).save(photo)
    prepare_reference(photo, tmp_path / name)
    return tmp_path / name


@pytest.mark.parametrize("shape", ["cylinder", "box"])
def test_flat_object_skips_refinement_and_textured_keeps_it(tmp_path: Path, shape: str) -> None:
    flat = plan_reference(_prepared(tmp_path, PhotoSpec(shape, "white", "flat", 31, size=384), "flat"))
    detailed = plan_reference(_prepared(tmp_path, PhotoSpec(shape, "grey", "print", 32, size=384), "print"))
    assert flat.highpass_refinement.action == "skip" and "flat texture" in flat.highpass_refinement.reason
    assert detailed.highpass_refinement.action == "run" and "fine detail" in detailed.highpass_refinement.reason
    threshold = PlanConfig().hf_threshold
    assert flat.highpass_refinement.measurements["hf_ratio"] < threshold
    assert detailed.highpass_refinement.measurements["hf_ratio"] >= threshold
    data = json.loads((tmp_path / "flat" / PLAN_FILE).read_text())
    assert data["skipped"] == ["highpass_refinement"]
    for key in ("segmentation", "highpass_refinement", "dmtet_grid", "export"):
        assert data[key]["reason"] and data[key]["action"] in ("run", "skip", "set")
    assert read_plan(tmp_path / "flat") == flat == StagePlan.from_json(flat.to_json())


def test_alpha_photo_skips_segmentation(tmp_path: Path) -> None:
    rgba = np.zeros((200, 160, 4), np.uint8)
    rgba[40:160, 40:120] = (30, 90, 200, 255)
    Image.fromarray(rgba).save(tmp_path / "cut.png")
    prepare_reference(tmp_path / "cut.png", tmp_path / "cut")
    plan = plan_reference(tmp_path / "cut")
    assert plan.segmentation.action == "skip" and "alpha" in plan.segmentation.reason
    assert plan.skipped == ["segmentation", "highpass_refinement"]  # and a flat blue box needs no refinement


def _info_and_rgba(tmp_path: Path):
    folder = _prepared(tmp_path, PhotoSpec("bottle", "white", "grain", 33, size=320), "bottle")
    info = read_reference(folder)
    return info, np.asarray(Image.open(folder / "rgba_256.png"))


def test_grid_follows_source_detail_and_face_limit(tmp_path: Path) -> None:
    info, rgba = _info_and_rgba(tmp_path)
    grids = []
    for px in (60, 150, 250, 2000):
        big = replace(info, bbox=(0, 0, px, px // 2))
        grids.append(make_plan(big, rgba).dmtet_grid.value)
    assert grids == sorted(grids) and grids[0] == 64 and grids[-1] == 128  # more source pixels → finer grid
    assert "min_grid" in make_plan(replace(info, bbox=(0, 0, 60, 30)), rgba).dmtet_grid.reason
    tight = make_plan(replace(info, bbox=(0, 0, 2000, 1000)), rgba, PlanConfig(extract_face_limit=70_000))
    assert tight.dmtet_grid.value < 128 and "face limit" in tight.dmtet_grid.reason
    est = tight.dmtet_grid.measurements["estimated_faces"]
    # The next grid step up would break the limit (the estimate is DMTet's own, faces ∝ n²).
    assert est <= 70_000 < est * ((tight.dmtet_grid.value + 16) / tight.dmtet_grid.value) ** 2
    assert est > 50_000 and tight.export.value == 50_000 and "decimate" in tight.export.reason


def test_plan_needs_a_prepared_reference(tmp_path: Path) -> None:
    (tmp_path / "half").mkdir()
    (tmp_path / "half" / "rgba_256.png").write_bytes(b"partial")
    with pytest.raises(FileNotFoundError, match="run `morpheus3d prepare` first"):
        plan_reference(tmp_path / "half")
    assert read_plan(tmp_path / "half") is None
