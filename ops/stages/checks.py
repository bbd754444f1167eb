"""The QA checks: which checks each stage's output gets, how a producing stage's checks are computed from its
manifest metrics, the verdict, and ``qa.json`` as the ``qa`` stage writes it.

Each check has a severity: ``error`` checks decide pass/fail, ``warn`` checks flag an asset for a
look without failing it. The producing stages' checks are pure functions of their manifest metrics,
so the Dagster asset checks and the QA report agree by construction.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from ops.engine.stage_ids import current_stage_id

QA_FILE = "qa.json"
ERROR, WARN = "error", "warn"


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


# The checks each stage's output gets, by stage id; the Dagster assets declare exactly these.
CHECKS: dict[str, tuple[CheckSpec, ...]] = {
    "reference": (CheckSpec("object_size", WARN, "the object covers at least qa.min_area_fraction of the photo"),),
    "nerf": (CheckSpec("stable_optimisation", WARN, "at most qa.max_guard_events NaN/Inf guard events"),),
    "dmtet": (CheckSpec("mesh_nonempty", ERROR, "the extracted mesh has faces"),
              CheckSpec("stable_optimisation", WARN, "at most qa.max_guard_events NaN/Inf guard events")),
    "texture": (CheckSpec("stable_optimisation", WARN, "at most qa.max_guard_events NaN/Inf guard events"),),
    "bake": (CheckSpec("reference_psnr", ERROR, "the GLB's reference view reaches qa.min_ref_psnr dB"),
             CheckSpec("uv_coverage", WARN, "the UV atlas covers at least qa.min_uv_coverage of the texture")),
    "export": (CheckSpec("formats_valid", ERROR, "the true-size GLB, the web GLB and the USDZ pass their formats' "
                                                 "validators (glTF-Validator, USD's ARKit checks) with 0 errors; "
                                                 "a warning where a validator could not run"),
               CheckSpec("true_size", WARN, "the size comes from the catalog (products.csv or export.*_mm) and its "
                                            "other dimensions agree with the mesh within qa.max_size_disagreement")),
    "qa": (CheckSpec("asset_finite", ERROR, "every vertex, UV and texel of the GLB is finite"),
           CheckSpec("mask_iou", ERROR, "the GLB's reference silhouette matches the photo's mask (IoU)"),
           CheckSpec("watertight", WARN, "the mesh is closed (an error when qa.require_watertight)"),
           CheckSpec("degenerate_faces", WARN, "at most qa.max_degenerate_fraction of the faces have ~zero area"),
           CheckSpec("colour_deviation", WARN, "novel views keep the photo's colours (a*b* histogram distance "
                                                "at most qa.max_colour_deviation)"),
           CheckSpec("hf_ratio", WARN, "novel views keep at least qa.min_hf_ratio of the photo's high-frequency "
                                        "detail"),
           CheckSpec("part_count", WARN, "the GLB has no more connected components than the photo's mask has "
                                         "silhouette parts (pieces of at least qa.min_part_share of its area)"),
           CheckSpec("parts_kept", ERROR, "from qa.part_views novel views, no region the NeRF shows larger than "
                                          "qa.max_missing_part_share of its silhouette is missing from the GLB, "
                                          "and the silhouette IoU stays at least qa.min_part_iou"),
           CheckSpec("verdict", ERROR, "no error-severity check failed in any stage")),
}


def check(spec: CheckSpec, passed: bool, value: Any, threshold: Any, message: str,
           severity: str | None = None) -> QACheck:
    if isinstance(value, float) and not math.isfinite(value):
        passed = False
    return QACheck(spec.name, bool(passed), severity or spec.severity, value, threshold, message)


def spec_of(stage: str, name: str) -> CheckSpec:
    return next(s for s in CHECKS[stage] if s.name == name)


def _guard_events(metrics: dict[str, Any]) -> int:
    return sum(int(v) for k, v in metrics.items() if k.startswith("guard_") and k != "guard_skipped_steps")


class CheckThresholds(Protocol):
    """The limits the stage checks compare against (``ops.stages.qa.QAConfig`` holds them)."""

    @property
    def min_ref_psnr(self) -> float: ...

    @property
    def min_uv_coverage(self) -> float: ...

    @property
    def min_area_fraction(self) -> float: ...

    @property
    def max_guard_events(self) -> int: ...

    @property
    def max_size_disagreement(self) -> float: ...


def stage_checks(stage: str, metrics: dict[str, Any], cfg: CheckThresholds) -> list[QACheck]:
    """The checks of a producing stage (not ``qa``), from its manifest metrics."""
    out: list[QACheck] = []
    for spec in CHECKS.get(stage, ()):
        if spec.name == "object_size":
            area = float(metrics.get("area_fraction", 0.0))
            out.append(check(spec, area >= cfg.min_area_fraction, area, cfg.min_area_fraction,
                              f"object covers {area:.1%} of the photo (minimum {cfg.min_area_fraction:.1%})"))
        elif spec.name == "stable_optimisation":
            events = _guard_events(metrics)
            out.append(check(spec, events <= cfg.max_guard_events, events, cfg.max_guard_events,
                              f"{events} NaN/Inf guard events (allowed {cfg.max_guard_events})"))
        elif spec.name == "mesh_nonempty":
            faces = int(metrics.get("faces", 0))
            out.append(check(spec, faces > 0, faces, 1, f"{faces} faces"))
        elif spec.name == "reference_psnr":
            value = float(metrics.get("ref_psnr", float("nan")))
            out.append(check(spec, value >= cfg.min_ref_psnr, value, cfg.min_ref_psnr,
                              f"reference view {value:.1f} dB (minimum {cfg.min_ref_psnr:.1f} dB)"))
        elif spec.name == "uv_coverage":
            value = float(metrics.get("uv_coverage", 0.0))
            out.append(check(spec, value >= cfg.min_uv_coverage, value, cfg.min_uv_coverage,
                              f"UV atlas covers {value:.1%} of the texture (minimum {cfg.min_uv_coverage:.1%})"))
        elif spec.name == "formats_valid":
            out.append(_formats_valid(spec, metrics))
        elif spec.name == "true_size":
            source, off = metrics.get("scale_source", "default"), float(metrics.get("size_disagreement", 0.0))
            ok = source != "default" and off <= cfg.max_size_disagreement
            why = ("no size in products.csv or export.height_mm: sized by export.default_height_mm"
                   if source == "default" else f"sized from {source}; other dimensions {off:.0%} off the mesh "
                                               f"(allowed {cfg.max_size_disagreement:.0%})")
            out.append(check(spec, ok, round(off, 4), cfg.max_size_disagreement, why))
        else:  # pragma: no cover - a CHECKS entry without an implementation is a programming error
            raise KeyError(f"no implementation for check {stage}.{spec.name}")
    return out


def _formats_valid(spec: CheckSpec, metrics: dict[str, Any]) -> QACheck:
    """Errors of every validated file; a validator that did not run makes this a warning, not a pass."""
    errors = {k.removesuffix("_errors"): int(v) for k, v in metrics.items() if k.endswith("_errors") and v}
    counted = [k for k in metrics if k.endswith("_errors")]
    if errors:
        detail = "; ".join(str(m) for k in errors for m in metrics.get(f"{k}_messages", [])[:3])
        return check(spec, False, sum(errors.values()), 0,
                     f"validator errors in {', '.join(f'{k} ({n})' for k, n in errors.items())}: {detail}")
    missing = metrics.get("gltf_validator", "not run")
    if missing != "ran" or not counted:
        return check(spec, False, None, 0, f"not validated: {missing}", severity=WARN)
    return check(spec, True, 0, 0, f"0 errors in {', '.join(k.removesuffix('_errors') for k in counted)}")


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
    weighted: dict[str, dict[str, Any]] = field(default_factory=dict)


def read_report(qa_dir: Path) -> QAReport:
    data = json.loads((Path(qa_dir) / QA_FILE).read_text(encoding="utf-8"))
    # Reports written before the stage ids were unified group their checks under the old ids.
    data["checks"] = {current_stage_id(stage): checks for stage, checks in data["checks"].items()}
    return QAReport(**data)
