"""Synthetic catalog rows following the pipeline's row convention (shared by the catalog, report tests and the
catalog benchmark): ids, plan, per-stage wall time/device/status, ``metric_*``, ``check_*``, paths."""

from __future__ import annotations

import datetime as dt
import random
from typing import Any

from ops.stages import STAGE_IDS

STAGES = STAGE_IDS
LOGGED_STAGES = ("nerf", "dmtet", "texture")  # the stages with an optimisation loop and a run log
METRICS = ("ref_psnr", "ssim_in", "mask_iou", "hf_ratio", "colour_deviation", "lpips", "uv_coverage",
           "texel_density", "watertight", "mesh_faces", "novel_view_clip", "silhouette_iou", "depth_consistency",
           "normal_smoothness", "edge_sharpness", "texture_entropy")
CHECKS = ("reference_psnr", "mask_iou", "uv_coverage", "watertight", "colour", "texture_seams", "faces",
          "lpips")
PRESETS = ("draft", "standard", "paper")


def synthetic_row(
    rng: random.Random,
    run_id: str,
    photo_key: str,
    created_at: dt.datetime,
    failed_at: str | None = None,
    paths: dict[str, str] | None = None,
) -> dict[str, Any]:
    """One row. ``failed_at``: the stage that failed (later stages skipped, no metrics, no verdict)."""
    failed_index = STAGES.index(failed_at) if failed_at else len(STAGES)
    row: dict[str, Any] = {
        "run_id": run_id,
        "photo_key": photo_key,
        "photo_sha256": f"{rng.getrandbits(256):064x}",
        "preset": rng.choice(PRESETS),
        "config_hash": f"{rng.getrandbits(64):016x}",
        "created_at": created_at,
        "status": "failed" if failed_at else "ok",
        "failure_reason": f"{failed_at}: FloatingPointError: loss became NaN at step {rng.randint(1, 500)}"
        if failed_at else None,
        "plan_refine": rng.choice(["none", "texture", "geometry+texture"]),
        "plan_grid": rng.choice([64, 96, 128]),
        "plan_export_faces": rng.choice([20000, 50000, 100000]),
    }
    for i, stage in enumerate(STAGES):
        ran = i <= failed_index
        row[f"{stage}_wall_s"] = rng.uniform(1.0, 120.0) if ran else None
        row[f"{stage}_device"] = rng.choice(["cpu", "cuda:0"]) if ran else None
        row[f"{stage}_status"] = ("failed" if i == failed_index else "ok") if ran else "skipped"
    psnr = rng.gauss(24.0, 3.0)
    metrics: dict[str, Any] = {
        "ref_psnr": psnr, "ssim_in": rng.uniform(0.6, 0.99), "mask_iou": rng.uniform(0.7, 1.0),
        "hf_ratio": rng.uniform(0.0, 0.3), "colour_deviation": rng.uniform(0.0, 0.2), "lpips": rng.uniform(0.05, 0.5),
        "uv_coverage": rng.uniform(0.4, 0.9), "texel_density": rng.uniform(100, 2000),
        "watertight": rng.random() < 0.8, "mesh_faces": float(rng.randint(5000, 100000)),
        "novel_view_clip": rng.uniform(0.2, 0.35), "silhouette_iou": rng.uniform(0.6, 1.0),
        "depth_consistency": rng.uniform(0.5, 1.0), "normal_smoothness": rng.uniform(0.0, 1.0),
        "edge_sharpness": rng.uniform(0.0, 5.0), "texture_entropy": rng.uniform(3.0, 8.0),
    }
    for name in METRICS:
        row[f"metric_{name}"] = None if failed_at else metrics[name]
    verdicts = []
    for name in CHECKS:
        check = None if failed_at else rng.choices(["pass", "warn", "fail"], [0.8, 0.15, 0.05])[0]
        row[f"check_{name}"] = check
        verdicts.append(check)
    if failed_at:
        row["verdict"] = None
    else:
        row["verdict"] = "fail" if "fail" in verdicts else "warn" if "warn" in verdicts else "pass"
    bad = [name for name, v in zip(CHECKS, verdicts, strict=True) if v in ("warn", "fail")]
    row["reasons"] = "; ".join(f"{name} below threshold" for name in bad)
    paths = paths or {}
    row["glb_path"] = paths.get("glb", f"{photo_key}/bake/asset.glb")
    row["preview_path"] = paths.get("preview", f"{photo_key}/qa/turntable.png")
    for stage in LOGGED_STAGES:  # a stage that never ran has no log
        ran = STAGES.index(stage) <= failed_index
        row[f"runlog_{stage}"] = paths.get(stage, f"{photo_key}/{stage}/runlog.parquet") if ran else None
    return row
