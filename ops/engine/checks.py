"""The QA checks' machinery, below the stages: what a check is (``CheckSpec``, declared on each ``Stage``), its
outcome (``QACheck``), the verdict over all of them and ``qa.json`` as the ``qa`` stage writes it.

Each check has a severity: ``error`` checks decide pass/fail, ``warn`` checks flag an asset for a look without
failing it. A producing stage's checks are a pure function of its manifest metrics (``Stage.judge``), so the
Dagster asset checks and the QA report agree by construction. The thresholds come from ``QAConfig``
(``ops.stages.qa``), seen here through ``CheckThresholds``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from ops.migrations import current_stage_id

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
    """A check a stage declares: its name, severity and what it asserts (the Dagster asset check's description)."""

    name: str
    severity: str
    description: str


def check(spec: CheckSpec, passed: bool, value: Any, threshold: Any, message: str,
          severity: str | None = None) -> QACheck:
    """The outcome of ``spec``; a non-finite value never passes. ``severity`` overrides the spec's (e.g. a check
    that could not run is a warning, not an error)."""
    if isinstance(value, float) and not math.isfinite(value):
        passed = False
    return QACheck(spec.name, bool(passed), severity or spec.severity, value, threshold, message)


class CheckThresholds(Protocol):
    """The limits the producing stages' checks compare against (``ops.stages.qa.QAConfig`` holds them)."""

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


# The optimising stages share one check: their loops count NaN/Inf guard events alike (``ops.engine.loop``).
STABLE_OPTIMISATION = CheckSpec("stable_optimisation", WARN, "at most qa.max_guard_events NaN/Inf guard events")


def stable_optimisation(metrics: dict[str, Any], cfg: CheckThresholds) -> list[QACheck]:
    """``STABLE_OPTIMISATION`` from an optimising stage's metrics (skipped steps are not events: counted apart)."""
    events = sum(int(v) for k, v in metrics.items() if k.startswith("guard_") and k != "guard_skipped_steps")
    return [check(STABLE_OPTIMISATION, events <= cfg.max_guard_events, events, cfg.max_guard_events,
                  f"{events} NaN/Inf guard events (allowed {cfg.max_guard_events})")]


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
