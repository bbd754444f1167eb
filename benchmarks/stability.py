"""Stiff and extreme settings: does every run finish, with finite outputs, and where does quality go?

Each entry is a set of overrides applied to all three optimising stages (or a differently framed
photo) and runs the whole pipeline to the GLB on one scene. Recorded: finished or the exception,
the numerical guards that fired (steps skipped for NaN/Inf priors, losses or gradients, rollbacks,
restores), whether every written tensor and the GLB are finite, and the final error.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import torch

from benchmarks.oracle import OracleConfig
from benchmarks.scene_eval import EvalConfig, evaluate, glb_output
from benchmarks.scene_runs import Schedule, photo_path, run_scene, schedule_store, stage_guards
from benchmarks.scenes import FRAME_FILL, Scene
from morpheus_core.render.textured import load_textured
from ops.config.presets import PipelineConfig
from ops.stages.bake import ASSET_GLB

log = logging.getLogger("morpheus3d.bench")

STAGES = ("nerf", "dmtet", "texture")
OPTIMISING = ("nerf", "dmtet", "texture")


def _all_stages(setting: str, value: object) -> tuple[str, ...]:
    return tuple(f"{s}.{setting}={value}" for s in STAGES)


def _t_range(t: float) -> tuple[str, ...]:
    """t pinned at one end; the bound that moves towards it is set first, so lo ≤ hi holds throughout."""
    lo, hi = _all_stages("guidance.t_lo", t), (*_all_stages("guidance.t_hi", t), f"nerf.guidance.t_hi_start={t}")
    return (*hi, *lo) if t > 0.5 else (*lo, *hi)


@dataclass(frozen=True)
class Entry:
    name: str
    overrides: tuple[str, ...] = ()
    fill: float = FRAME_FILL  # photo framing: < 0.8 a small object, > 1 cut by the borders
    lr_factor: float = 1.0  # every learning rate of the three stages, relative to the schedule's own

    def settings(self, cfg: PipelineConfig) -> tuple[str, ...]:
        """The entry's overrides, with the learning rates read from ``cfg`` and scaled."""
        if self.lr_factor == 1.0:
            return self.overrides
        lrs = tuple(f"{stage}.{f.name}={getattr(getattr(cfg, stage), f.name) * self.lr_factor:g}"
                    for stage in STAGES for f in fields(getattr(cfg, stage)) if f.name.startswith("lr_"))
        return (*self.overrides, *lrs)

    @property
    def aligned(self) -> bool:
        """Whether the reconstruction shares the ground truth's frame (a cut-off photo does not)."""
        return self.fill <= 1.0


ENTRIES: tuple[Entry, ...] = (
    Entry("defaults"),
    *(Entry(f"lambda_c={v:g}", _all_stages("guidance.lambda_c", v)) for v in (0.0, 0.5, 1.0)),
    *(Entry(f"k2d={k:g}", (f"texture.guidance.k2d={k}",)) for k in (10.0, 50.0)),
    Entry("k3d=50", _all_stages("guidance.k3d", 50.0)),
    Entry("lr x10", lr_factor=10.0),
    *(Entry(f"r={r:g}", (f"texture.guidance.r={r}",)) for r in (0.0, 1.0)),
    *(Entry(p, _all_stages("loop.precision", p)) for p in ("bfloat16", "float16")),
    Entry("t=0", _t_range(0.0)),
    Entry("t=1", _t_range(1.0)),
    Entry("tiny object (8% of the photo)", fill=0.08),
    # Its mask touches every border, so the mask confidence would stop it before the optimising stages
    # (as it should for a user's photo): accepted here, since what is tested is their numerics.
    Entry("frame-filling (cut by the borders)", ("reference.prepare.segment.min_confidence=0",), fill=1.15),
)


def _finite_glb(path: Path) -> bool:
    asset = load_textured(path)
    return all(bool(torch.isfinite(t).all()) for t in (asset.vertices, asset.uvs, asset.texture))


def run_stability(scene: Scene, schedule: Schedule, device: str, work: Path, eval_cfg: EvalConfig,
                  entries: tuple[Entry, ...] = ENTRIES, oracle: OracleConfig | None = None) -> list[dict[str, Any]]:
    store = schedule_store(work, schedule)
    dev = torch.device("cuda" if device == "cuda" else "cpu")
    records = []
    for i, entry in enumerate(entries):
        key = f"{scene.name}_{i:02d}"
        rec: dict[str, Any] = {"entry": entry.name, "scene": scene.name, "overrides": list(entry.overrides),
                               "fill": entry.fill, "aligned": entry.aligned}
        try:
            base = schedule.config(device, ("texture.follow_plan=false",))
            rec["overrides"] = list(entry.settings(base))
            cfg = schedule.config(device, ("texture.follow_plan=false", *rec["overrides"]))
            out = run_scene(scene, photo_path(scene, work / "photos", entry.fill), store, cfg, schedule.label, key,
                            until="bake", oracle=oracle)
            rec["finished"] = out.error is None
            rec["error"] = out.error
        except Exception as exc:
            rec["finished"], rec["error"] = False, f"unhandled {type(exc).__name__}: {exc}"
        rec["guards"] = {stage: stage_guards(store, key, stage) for stage in OPTIMISING}
        rec["guard_events"] = sum(sum(g.values()) for g in rec["guards"].values())
        if rec["finished"]:
            glb = store.stage_dir(key, "bake") / ASSET_GLB
            rec["finite_outputs"] = _finite_glb(glb)
            metrics = evaluate(glb_output(glb, dev), scene, eval_cfg)
            rec["ref_psnr_glb"] = store.read_manifest(key, "bake").metrics.get("ref_psnr")
            if entry.aligned:
                rec.update({k: metrics[k] for k in ("novel_psnr", "colour_deviation", "chamfer")})
            rec["finite_metrics"] = all(v is None or math.isfinite(v) for v in metrics.values())
        log.info("stability %-36s finished=%s guards=%s error=%s", entry.name, rec["finished"],
                 rec["guard_events"], rec.get("error"))
        records.append(rec)
    return records
