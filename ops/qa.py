"""The QA gate: does an asset ship? Checks on every stage's output, and the final ``qa`` stage.

Each check has a severity: ``error`` checks decide pass/fail, ``warn`` checks flag an asset for a
look without failing it. Thresholds come from ``QAConfig`` (``--set qa.min_ref_psnr=18``). The
checks of the producing stages are pure functions of their manifest metrics, so the Dagster
assets and the QA report agree by construction; the ``qa`` stage re-loads the written GLB and
measures it on its own (reference-view PSNR, mask IoU, finiteness, mesh health) rather than
trusting the numbers the bake reported.

Output of the ``qa`` stage: ``qa.json`` (verdict, reasons, every check and metric) and
``turntable.png`` (the GLB from ``turntable_views`` angles).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from assets_store.atomic import atomic_write_text
from morpheus_core.cameras import turntable
from morpheus_core.render.textured import load_textured, render_textured
from ops.stage_common import ReferenceTarget, StageResult, pick_device, reference_psnr, save_strip

QA_FILE = "qa.json"
QA_TURNTABLE_FILE = "turntable.png"
CODE_VERSION = "qa-1"
ERROR, WARN = "error", "warn"


@dataclass(frozen=True)
class QAConfig:
    """Thresholds of the QA checks. Defaults sit below what the draft preset reaches on the
    bundled photos (GLB reference PSNR 19–23 dB, mask IoU > 0.9), so a failing check means a
    broken asset, not a coarse one."""

    min_ref_psnr: float = 15.0
    min_mask_iou: float = 0.80
    min_uv_coverage: float = 0.25
    min_area_fraction: float = 0.02
    max_guard_events: int = 10
    require_watertight: bool = False
    eval_resolution: int = 256
    turntable_views: int = 8
    preview_size: int = 128

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_mask_iou <= 1.0 or not 0.0 <= self.min_uv_coverage <= 1.0:
            raise ValueError("qa.min_mask_iou and qa.min_uv_coverage must lie in [0, 1]")
        if self.eval_resolution < 16 or self.turntable_views < 1:
            raise ValueError("qa.eval_resolution must be >= 16 and qa.turntable_views >= 1")


@dataclass(frozen=True)
class QACheck:
    """One check's outcome: ``value`` against ``threshold``; ``message`` says it for people."""

    name: str
    passed: bool
    severity: str
    value: Any
    threshold: Any
    message: str


@dataclass(frozen=True)
class CheckSpec:
    name: str
    severity: str
    description: str


# The checks each stage's output gets, by stage name; the Dagster assets declare exactly these.
CHECKS: dict[str, tuple[CheckSpec, ...]] = {
    "reference": (CheckSpec("object_size", WARN, "the object covers at least qa.min_area_fraction of the photo"),),
    "nerf_fit": (CheckSpec("stable_optimisation", WARN, "at most qa.max_guard_events NaN/Inf guard events"),),
    "dmtet": (CheckSpec("mesh_nonempty", ERROR, "the extracted mesh has faces"),
              CheckSpec("stable_optimisation", WARN, "at most qa.max_guard_events NaN/Inf guard events")),
    "texture_refine": (CheckSpec("stable_optimisation", WARN, "at most qa.max_guard_events NaN/Inf guard events"),),
    "uv_bake": (CheckSpec("reference_psnr", ERROR, "the GLB's reference view reaches qa.min_ref_psnr dB"),
                CheckSpec("uv_coverage", WARN, "the UV atlas covers at least qa.min_uv_coverage of the texture")),
    "qa": (CheckSpec("asset_finite", ERROR, "every vertex, UV and texel of the GLB is finite"),
           CheckSpec("mask_iou", ERROR, "the GLB's reference silhouette matches the photo's mask (IoU)"),
           CheckSpec("watertight", WARN, "the mesh is closed (an error when qa.require_watertight)"),
           CheckSpec("verdict", ERROR, "no error-severity check failed in any stage")),
}


def _check(spec: CheckSpec, passed: bool, value: Any, threshold: Any, message: str,
           severity: str | None = None) -> QACheck:
    if isinstance(value, float) and not math.isfinite(value):
        passed = False
    return QACheck(spec.name, bool(passed), severity or spec.severity, value, threshold, message)


def _spec(stage: str, name: str) -> CheckSpec:
    return next(s for s in CHECKS[stage] if s.name == name)


def _guard_events(metrics: dict[str, Any]) -> int:
    return sum(int(v) for k, v in metrics.items() if k.startswith("guard_") and k != "guard_skipped_steps")


def stage_checks(stage: str, metrics: dict[str, Any], cfg: QAConfig) -> list[QACheck]:
    """The checks of a producing stage (not ``qa``), from its manifest metrics."""
    out: list[QACheck] = []
    for spec in CHECKS.get(stage, ()):
        if spec.name == "object_size":
            area = float(metrics.get("area_fraction", 0.0))
            out.append(_check(spec, area >= cfg.min_area_fraction, area, cfg.min_area_fraction,
                              f"object covers {area:.1%} of the photo (minimum {cfg.min_area_fraction:.1%})"))
        elif spec.name == "stable_optimisation":
            events = _guard_events(metrics)
            out.append(_check(spec, events <= cfg.max_guard_events, events, cfg.max_guard_events,
                              f"{events} NaN/Inf guard events (allowed {cfg.max_guard_events})"))
        elif spec.name == "mesh_nonempty":
            faces = int(metrics.get("faces", 0))
            out.append(_check(spec, faces > 0, faces, 1, f"{faces} faces"))
        elif spec.name == "reference_psnr":
            value = float(metrics.get("ref_psnr", float("nan")))
            out.append(_check(spec, value >= cfg.min_ref_psnr, value, cfg.min_ref_psnr,
                              f"reference view {value:.1f} dB (minimum {cfg.min_ref_psnr:.1f} dB)"))
        elif spec.name == "uv_coverage":
            value = float(metrics.get("uv_coverage", 0.0))
            out.append(_check(spec, value >= cfg.min_uv_coverage, value, cfg.min_uv_coverage,
                              f"UV atlas covers {value:.1%} of the texture (minimum {cfg.min_uv_coverage:.1%})"))
        else:  # pragma: no cover - a CHECKS entry without an implementation is a programming error
            raise KeyError(f"no implementation for check {stage}.{spec.name}")
    return out


def mask_iou(opacity: torch.Tensor, mask: torch.Tensor) -> float:
    """IoU of two silhouettes thresholded at 0.5; 1.0 when both are empty (nothing to disagree on)."""
    a, b = opacity.detach().float() > 0.5, mask.detach().float() > 0.5
    union = int((a | b).sum())
    return 1.0 if union == 0 else int((a & b).sum()) / union


def verdict(checks: list[QACheck]) -> tuple[str, list[str]]:
    """``fail`` when an error check failed, ``warn`` when only warnings did, else ``pass``; with reasons."""
    failed = [c for c in checks if not c.passed]
    reasons = [f"{c.name}: {c.message}" for c in failed]
    if any(c.severity == ERROR for c in failed):
        return "fail", reasons
    return ("warn" if failed else "pass"), reasons


@dataclass
class QAReport:
    """What ``qa.json`` holds."""

    verdict: str
    reasons: list[str]
    checks: dict[str, list[dict[str, Any]]]
    metrics: dict[str, Any]
    prior: str = ""
    notes: list[str] = field(default_factory=list)


def read_report(qa_dir: Path) -> QAReport:
    data = json.loads((Path(qa_dir) / QA_FILE).read_text(encoding="utf-8"))
    return QAReport(**data)


def run_qa(reference_dir: Path, glb_path: Path, out_dir: Path, cfg: QAConfig,
           upstream: dict[str, dict[str, Any]], prior: str = "", device: str = "auto") -> StageResult:
    """Measure the written GLB and gather every stage's checks into ``qa.json``.

    ``upstream`` maps stage name → its manifest metrics (the producing stages' checks are
    re-evaluated here with this config's thresholds, so the verdict is one consistent decision).
    """
    import trimesh

    dev = pick_device(device)
    asset = load_textured(glb_path).to(dev)
    r = cfg.eval_resolution
    target = ReferenceTarget.load(reference_dir, r, dev)
    finite = all(bool(torch.isfinite(t).all()) for t in (asset.vertices, asset.uvs, asset.texture))
    checks: dict[str, list[QACheck]] = {s: stage_checks(s, m, cfg) for s, m in upstream.items() if s in CHECKS}
    own: list[QACheck] = [_check(_spec("qa", "asset_finite"), finite, finite, True,
                                 "finite" if finite else "the GLB holds NaN/Inf values")]
    metrics: dict[str, Any] = {"faces": int(asset.faces.shape[0]), "vertices": int(asset.vertices.shape[0])}
    if finite:
        with torch.no_grad():
            ref = render_textured(asset, target.camera, r, r)
            views = render_textured(asset, turntable(cfg.turntable_views, 15.0).to(dev), r, r).rgb_chw()
        metrics["ref_psnr"] = reference_psnr(ref.rgb_chw(), target)
        metrics["mask_iou"] = round(mask_iou(ref.opacity_chw(), target.mask), 4)
        save_strip(Path(out_dir) / QA_TURNTABLE_FILE, list(views), cfg.preview_size)
        own.append(_check(_spec("qa", "mask_iou"), metrics["mask_iou"] >= cfg.min_mask_iou, metrics["mask_iou"],
                          cfg.min_mask_iou, f"silhouette IoU {metrics['mask_iou']:.3f} (minimum {cfg.min_mask_iou})"))
    else:
        own.append(_check(_spec("qa", "mask_iou"), False, None, cfg.min_mask_iou, "not measured: non-finite asset"))
    welded = trimesh.Trimesh(asset.vertices.cpu().numpy(), asset.faces.cpu().numpy(), process=True)
    components = len(welded.split(only_watertight=False)) if len(welded.faces) else 0
    metrics.update({"watertight": bool(welded.is_watertight), "components": int(components),
                    "euler_number": int(welded.euler_number)})
    severity = ERROR if cfg.require_watertight else WARN
    own.append(_check(_spec("qa", "watertight"), metrics["watertight"], metrics["watertight"], True,
                      "closed" if metrics["watertight"] else "the mesh has open edges", severity))
    everything = [c for cs in checks.values() for c in cs] + own
    decision, reasons = verdict(everything)
    own.append(_check(_spec("qa", "verdict"), decision != "fail", decision, "pass or warn",
                      "; ".join(reasons) if reasons else "every check passed"))
    checks["qa"] = own
    report = QAReport(decision, reasons, {s: [asdict(c) for c in cs] for s, cs in checks.items()},
                      _finite_json(metrics), prior)
    atomic_write_text(Path(out_dir) / QA_FILE, json.dumps(asdict(report), indent=2, sort_keys=True, default=str))
    return StageResult({**metrics, "verdict": decision, "failed_checks": len(reasons)}, "none (qa)", str(dev))


def _finite_json(metrics: dict[str, Any]) -> dict[str, Any]:
    """JSON has no NaN/Inf: non-finite numbers become None (and the checks already failed on them)."""
    return {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in metrics.items()}
