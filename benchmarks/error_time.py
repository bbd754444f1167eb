"""Error against run time: each schedule run end to end on the scenes, scored after every stage.

A point per stage end: cumulative wall time (from the stage manifests) against novel-view PSNR and
Chamfer distance to the ground truth — NeRF (volume render), DMTet (mesh + its texture field),
texture refinement, and the exported GLB as a user receives it. The stages' own logs add the
reference-view PSNR curve inside each stage.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import torch

from assets_store.store import Store
from benchmarks.oracle import OracleConfig
from benchmarks.scene_eval import EvalConfig, Reconstruction, evaluate, glb_output, mesh_output, nerf_output
from benchmarks.scene_runs import Schedule, photo_path, run_scene, runlog_curve, schedule_store, stage_wall_s
from benchmarks.scenes import Scene
from ops.stages.bake import ASSET_GLB

log = logging.getLogger("morpheus3d.bench")

POINTS = ("nerf", "dmtet", "texture", "bake")


def _stage_output(store: Store, key: str, stage: str, schedule_cfg: Any, dev: torch.device) -> Reconstruction:
    if stage == "nerf":
        return nerf_output(store, key, schedule_cfg.nerf.render, dev)
    if stage == "bake":
        return glb_output(store.stage_dir(key, "bake") / ASSET_GLB, dev)
    return mesh_output(store, key, stage, dev)


def run_error_time(scenes: list[Scene], schedules: list[Schedule], device: str, work: Path,
                   eval_cfg: EvalConfig, oracle: OracleConfig | None = None) -> list[dict[str, Any]]:
    """One record per (schedule, scene): per-stage points and the stages' reference-PSNR curves."""
    dev = torch.device("cuda" if device == "cuda" else "cpu")
    records = []
    for schedule in schedules:
        store = schedule_store(work, schedule)
        cfg = schedule.config(device, ("texture.follow_plan=false",))
        for scene in scenes:
            out = run_scene(scene, photo_path(scene, work / "photos"), store, cfg, schedule.label, scene.name,
                            until="bake", oracle=oracle)
            if out.error:
                records.append({"schedule": schedule.label, "scene": scene.name, "error": out.error})
                continue
            elapsed, points, curves = stage_wall_s(store, scene.name, "reference"), [], {}
            for stage in POINTS:
                elapsed += stage_wall_s(store, scene.name, stage)
                metrics = evaluate(_stage_output(store, scene.name, stage, cfg, dev), scene, eval_cfg)
                points.append({"stage": stage, "wall_s": round(elapsed, 2), **metrics})
                curves[stage] = runlog_curve(store, scene.name, stage)
            records.append({"schedule": schedule.label, "scene": scene.name, "points": points, "curves": curves})
            log.info("%s %s: %.0f s, GLB novel PSNR %.2f dB, Chamfer %.4f", schedule.label, scene.name,
                     points[-1]["wall_s"], points[-1]["novel_psnr"], points[-1]["chamfer"])
    return records
