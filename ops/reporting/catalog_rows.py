"""One catalog row per photo per run, built from the store's manifests and the QA report.

The row convention (``assets_store.catalog``): keys and hashes, preset, plan decisions, per stage
``<stage>_wall_s`` / ``<stage>_device`` / ``<stage>_status`` / ``<stage>_built_at``, every QA metric as
``metric_<name>``, every check as ``check_<stage>_<name>`` (pass / warn / fail), the verdict and its reasons,
where the GLB, the preview and each stage's run log are, and why the run failed when it did.

A row counts the work its run did, once: ``<stage>_wall_s`` is the time this run spent making the stage's
output, 0 when the run found the output cached (``<stage>_status`` ``cached``), and ``work_s`` their sum. A
run that found every stage cached still gets its row (the run happened), with ``status`` ``cached`` and
``work_s`` 0. ``<stage>_built_at`` (the output's manifest time) names the output, so a reader can tell
whether two rows describe the same piece of work. When the caller does not say what a stage did (the Dagster
QA step knows only its own stage), the photo's earlier rows decide: an output one of them already reported is
cached here; rows from before ``<stage>_built_at`` are matched by their wall time, which they copied.
"""

from __future__ import annotations

import math
import uuid
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.compute as pc

from assets_store.catalog import Catalog
from assets_store.manifest import Manifest
from assets_store.store import Store
from ops.engine.artifacts import RUNLOG_FILE
from ops.engine.checks import QA_FILE, read_report
from ops.engine.viewer_page import VIEWER_FILE
from ops.migrations import RENAMED_STAGES
from ops.pipeline.photo_run import PhotoOutcome
from ops.reporting.stage_columns import NOT_WORK, current_stage_columns
from ops.stages import STAGE_IDS
from ops.stages.bake import ASSET_GLB
from ops.stages.export import MODEL_GLB, MODEL_USDZ, MODEL_WEB_GLB
from ops.stages.qa import QA_TURNTABLE_FILE

CACHED = "cached"
UNSAID = "present"  # the output is there and no earlier row reported it; the caller did not say which run made it


def _number(value: Any) -> Any:
    if isinstance(value, bool) or value is None:
        return value
    if isinstance(value, (int, float)):
        return float(value) if math.isfinite(value) else None
    return None


def built_at(manifest: Manifest) -> datetime | None:
    """When the output was made (its manifest's time, UTC); None for a manifest whose time does not parse."""
    try:
        made = datetime.fromisoformat(manifest.created_at)
    except (TypeError, ValueError):
        return None
    return made.astimezone(timezone.utc) if made.tzinfo is not None else None


def reported_outputs(catalog: Catalog, key: str, manifests: dict[str, Manifest]) -> set[str]:
    """The stages of ``manifests`` whose output an earlier row of photo ``key`` already reported: the same
    ``<stage>_built_at``, or, in a row from before that column, the same ``<stage>_wall_s``."""
    times = {stage: built_at(m) for stage, m in manifests.items()}
    known = [t for t in times.values() if t is not None]
    # A row reporting an output was written after the output was made: older days need not be opened.
    since = min(known) if len(known) == len(times) and known else None
    old_ids = {new: old for old, new in RENAMED_STAGES.items()}
    columns = ["photo_key"]
    for stage in manifests:
        columns += [f"{stage}_built_at", f"{stage}_wall_s"]
        if stage in old_ids:
            columns.append(f"{old_ids[stage]}_wall_s")
    table = catalog.read(since, columns)
    if table.num_rows == 0:
        return set()
    table = current_stage_columns(table.filter(pc.fill_null(pc.equal(table["photo_key"], key), False)))
    found = set()
    for stage, m in manifests.items():
        made = times[stage]
        at = table[f"{stage}_built_at"].to_pylist() if f"{stage}_built_at" in table.column_names else []
        if made is not None and made in at:
            found.add(stage)
            continue
        if f"{stage}_wall_s" not in table.column_names or table[f"{stage}_wall_s"].null_count == table.num_rows:
            continue
        walls = np.asarray(pc.fill_null(table[f"{stage}_wall_s"].cast("float64"), np.nan))
        undated = np.array([a is None for a in at]) if at else np.ones(len(walls), dtype=bool)
        if np.any(undated & (walls == float(m.wall_time_s))):
            found.add(stage)
    return found


def photo_row(store: Store, key: str, run_id: str, status_by_stage: dict[str, str] | None = None,
              failure: str | None = None, photo_sha256: str | None = None) -> dict[str, Any]:
    """The row for ``key`` as the store holds it now. ``status_by_stage``: what this run did per
    stage (ran / resumed / cached / skipped / failed); ``failure``: why the run failed. A stage
    not named is looked up in the photo's earlier rows (see the module docstring)."""
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
    statuses = dict(status_by_stage or {})
    unsaid = {stage: m for stage, m in manifests.items() if stage not in statuses}
    if unsaid:
        seen = reported_outputs(Catalog(store.catalog_dir), key, unsaid)
        statuses.update({stage: CACHED if stage in seen else UNSAID for stage in unsaid})
    work = 0.0
    for stage in STAGE_IDS:
        m = manifests.get(stage)
        status = statuses.get(stage, "missing" if m is None else UNSAID)
        wall = None
        if m is not None and status not in NOT_WORK:
            wall = float(m.wall_time_s)
            work += wall
        elif m is not None and status == CACHED:
            wall = 0.0  # found made: the time it took belongs to the row of the run that made it
        row[f"{stage}_wall_s"] = wall
        row[f"{stage}_device"] = m.device if m else None
        row[f"{stage}_status"] = status
        row[f"{stage}_built_at"] = built_at(m) if m else None
        log = store.stage_dir(key, stage) / RUNLOG_FILE
        if m is not None and RUNLOG_FILE in m.outputs:
            row[f"runlog_{stage}"] = str(log)
    row["work_s"] = round(work, 3)
    if not failure and manifests and all(statuses.get(s) in NOT_WORK for s in manifests):
        row["status"] = CACHED  # the run happened and did nothing: it found every output made
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
    if "export" in manifests:
        row.update(export_columns(manifests["export"].metrics, store.stage_dir(key, "export")))
        if (qa_dir / VIEWER_FILE).is_file():
            row["viewer_path"] = str(qa_dir / VIEWER_FILE)
    return row


def export_columns(metrics: dict[str, Any], export_dir: Path) -> dict[str, Any]:
    """The catalog's view of the export: the SKU, the real size in millimetres and where it came from, the
    file sizes, and where the true-size, web and USDZ files are."""
    out: dict[str, Any] = {"sku": metrics.get("sku") or None, "scale_source": metrics.get("scale_source")}
    for name in ("height_mm", "width_mm", "depth_mm", "size_disagreement", "glb_bytes", "web_glb_bytes",
                 "usdz_bytes"):
        out[f"export_{name}"] = _number(metrics.get(name))
    out["model_glb_path"] = str(export_dir / MODEL_GLB)
    out["web_glb_path"] = str(export_dir / MODEL_WEB_GLB)
    if metrics.get("usdz_bytes"):
        out["usdz_path"] = str(export_dir / MODEL_USDZ)
    return out


def record_outcomes(store: Store, outcomes: list[PhotoOutcome], run_id: str | None = None) -> None:
    """Append one catalog row per photo of a ``morpheus3d run`` (one run id for the whole command)."""
    run_id = run_id or f"cli-{uuid.uuid4().hex[:12]}"
    rows = [photo_row(store, o.key, run_id, {s.stage: s.status for s in o.stages}, o.error) for o in outcomes]
    if rows:
        Catalog(store.catalog_dir).append(rows)
