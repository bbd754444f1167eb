"""Stage 0: the photo segmented and recentred (``ops.intake.prepare``), and the plan for the later
stages (``ops.intake.plan``). CPU only; seconds per photo."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ops.engine.checks import WARN, CheckSpec, CheckThresholds, QACheck, check
from ops.engine.previews import PREVIEW_FILE, save_mask_overlay
from ops.engine.stage import Stage, StageContext, StageWork
from ops.engine.stage_job import StageResult
from ops.intake.plan import PLAN_FILE, PlanConfig, plan_reference
from ops.intake.prepare import REFERENCE_FILE, PrepareConfig, prepare_reference

CODE_VERSION = "reference-3"  # 2: the mask-overlay preview; 3: edge cue, every part, confidence


@dataclass(frozen=True)
class ReferenceStageConfig:
    prepare: PrepareConfig = field(default_factory=PrepareConfig)
    plan: PlanConfig = field(default_factory=PlanConfig)


def _build(ctx: StageContext, cfg: ReferenceStageConfig) -> StageWork:

    def body(out: Path, _ckpt: Path | None) -> StageResult:
        info = prepare_reference(ctx.photo, out, cfg.prepare)
        plan = plan_reference(out, cfg.plan)
        save_mask_overlay(out, out)
        return StageResult({"method": info.method, "area_fraction": round(info.area_fraction, 4),
                            "parts": info.kept_parts, "mask_confidence": info.confidence["score"],
                            "warnings": len(info.warnings), "plan": plan.summary()},
                           "none (segmentation)", "cpu", list(info.warnings))

    # The config keys are those the fingerprints of existing stores were hashed with.
    return StageWork({"prepare": cfg.prepare, "plan": cfg.plan}, body, inputs={"photo": ctx.photo_hash()})


OBJECT_SIZE = CheckSpec("object_size", WARN, "the object covers at least qa.min_area_fraction of the photo")


def _judge(metrics: dict[str, Any], cfg: CheckThresholds) -> list[QACheck]:
    area = float(metrics.get("area_fraction", 0.0))
    return [check(OBJECT_SIZE, area >= cfg.min_area_fraction, area, cfg.min_area_fraction,
                  f"object covers {area:.1%} of the photo (minimum {cfg.min_area_fraction:.1%})")]


STAGE = Stage(
    "reference", CODE_VERSION, config=ReferenceStageConfig, reads=(),
    writes=(REFERENCE_FILE, PLAN_FILE, "rgba_<size>.png", "mask_<size>.png", PREVIEW_FILE), preview=PREVIEW_FILE,
    gpu=False, cpu_only=True, build=_build, checks=(OBJECT_SIZE,), judge=_judge,
    description="Segmentation, mask and recentred reference views of the photo, plus the stage plan "
                "(DMTet grid, whether high-pass refinement pays, export face budget).")
