"""One catalog row per photo per run, built from the store's manifests and the QA report.

The row convention (``assets_store.catalog``): keys and hashes, preset, plan decisions, per stage
``<stage>_wall_s`` / ``<stage>_device`` / ``<stage>_status``, every QA metric as ``metric_<name>``,
every check as ``check_<stage>_<name>`` (pass / warn / fail), the verdict and its reasons, where
the GLB, the preview and each stage's run log are, and why the run failed when it did.
"""

from __future__ import annotations

import math
import uuid
from datetime import datetime, timezone
from typing import Any

from assets_store.catalog import Catalog
from assets_store.manifest import Manifest
from assets_store.store import Store
from ops.engine.artifacts import RUNLOG_FILE
from ops.engine.pipeline import PhotoOutcome
from ops.engine.stage_ids import STAGE_IDS
from ops.stages.bake import ASSET_GLB
from ops.stages.checks import QA_FILE, read_report
from ops.stages.qa import QA_TURNTABLE_FILE


def _number(value: Any) -> Any:
    if isinstance(value, bool) or value is None:
        return value
    if isinstance(value, (int, float)):
        return float(value) if math.isfinite(value) else None
    return None


def photo_row(store: Store, key: str, run_id: str, status_by_stage: dict[str, str] | None = None,
              failure: str | None = None, photo_sha256: str | None = None) -> dict[str, Any]:
    """The row for ``key`` as the store holds it now. ``status_by_stage``: what this run did per
    stage (ran / resumed / cached / skipped / failed); ``failure``: why the run failed."""
    manifests: dict[str, Manifest] = {}
    for stage in STAGE_IDS:
        m = store.read_manifest(key, stage)
        if m is not None:
            manifests[stage] = m
    ref = manifests.get("reference")
    row: dict[str, Any] = {
        "run_id": run_id, "photo_key": key,
        "photo_sha256": photo_sha256 or (ref.fingerprint.inputs.get("photo") if ref else None),
        "preset": next((m.preset for m in manifests.values() if m.preset), None),
        "config_hash": manifests["qa"].fingerprint.config_hash if "qa" in manifests else None,
        "created_at": datetime.now(timezone.utc),
        "status": "failed" if failure else "ok", "failure_reason": failure,
    }
    plan = next((m.plan for m in manifests.values() if m.plan), {})
    row.update({"plan_refine": plan.get("refine"), "plan_grid": plan.get("grid"),
                "plan_export_faces": plan.get("export_faces")})
    statuses = status_by_stage or {}
    for stage in STAGE_IDS:
        m = manifests.get(stage)
        row[f"{stage}_wall_s"] = float(m.wall_time_s) if m else None
        row[f"{stage}_device"] = m.device if m else None
        row[f"{stage}_status"] = statuses.get(stage, "present" if m else "missing")
        log = store.stage_dir(key, stage) / RUNLOG_FILE
        if m is not None and RUNLOG_FILE in m.outputs:
            row[f"runlog_{stage}"] = str(log)
    qa_dir = store.stage_dir(key, "qa")
    if "qa" in manifests and (qa_dir / QA_FILE).is_file():
        report = read_report(qa_dir)
        row["verdict"] = report.verdict
        row["reasons"] = "; ".join(report.reasons)
        for name, value in report.metrics.items():
            number = _number(value)
            if number is not None or value is None:
                row[f"metric_{name}"] = number
        for stage, checks in report.checks.items():
            for c in checks:
                row[f"check_{stage}_{c['name']}"] = "pass" if c["passed"] else c["severity"].replace("error", "fail")
        row["preview_path"] = str(qa_dir / QA_TURNTABLE_FILE)
    else:
        row["verdict"] = None
    if "bake" in manifests:
        row["glb_path"] = str(store.stage_dir(key, "bake") / ASSET_GLB)
    return row


def record_outcomes(store: Store, outcomes: list[PhotoOutcome], run_id: str | None = None) -> None:
    """Append one catalog row per photo of a ``morpheus3d run`` (one run id for the whole command)."""
    run_id = run_id or f"cli-{uuid.uuid4().hex[:12]}"
    rows = [photo_row(store, o.key, run_id, {s.stage: s.status for s in o.stages}, o.error) for o in outcomes]
    if rows:
        Catalog(store.catalog_dir).append(rows)
