"""What a materialisation shows in the UI: timing, device, cache hit, plan decisions, key metrics,
artifact paths and an inline preview image (base64 PNG in Markdown, so it renders in place)."""

from __future__ import annotations

import base64
import math
from pathlib import Path
from typing import Any

from dagster import MetadataValue

from assets_store.manifest import Manifest
from ops.engine.checks import QACheck
from ops.pipeline.photo_run import StageOutcome
from ops.stages import BY_ID

MAX_PREVIEW_BYTES = 400_000  # the UI stores metadata in the event log: keep it small


def preview_markdown(path: Path, caption: str) -> MetadataValue | None:
    try:
        data = path.read_bytes()
    except OSError:
        return None
    if len(data) > MAX_PREVIEW_BYTES:
        return MetadataValue.md(f"{caption}: preview too large to inline, see `{path}`")
    encoded = base64.b64encode(data).decode("ascii")
    return MetadataValue.md(f"**{caption}**\n\n![{caption}](data:image/png;base64,{encoded})")


def _plain(value: Any) -> Any:
    if isinstance(value, float):
        return round(value, 4) if math.isfinite(value) else str(value)
    return value


def stage_metadata(outcome: StageOutcome, stage_dir: Path) -> dict[str, Any]:
    m: Manifest | None = outcome.manifest
    if m is None:  # pragma: no cover - a failed stage raises before metadata is built
        return {"status": outcome.status}
    meta: dict[str, Any] = {
        "status": outcome.status,
        "cache_hit": outcome.status == "cached",
        "wall_time_s": MetadataValue.float(float(m.wall_time_s)),
        "device": m.device,
        "preset": m.preset,
        "prior": m.prior,
        "code_version": m.fingerprint.code_version,
        "config_hash": m.fingerprint.config_hash[:12],
        "created_at": m.created_at,
        "stage_dir": MetadataValue.path(str(stage_dir)),
    }
    if outcome.lease is not None:
        meta["gpu_lease"] = outcome.lease
    if m.plan:
        meta["plan"] = MetadataValue.json({k: _plain(v) for k, v in m.plan.items()})
    metrics = {k: _plain(v) for k, v in m.metrics.items() if isinstance(v, (int, float, str, bool)) or v is None}
    meta["metrics"] = MetadataValue.json(metrics)
    for name in ("ref_psnr", "faces", "uv_coverage", "mask_iou", "steps_run", "steps_saved", "resumed_from_step",
                 "verdict"):
        value = m.metrics.get(name)
        if value is not None:
            meta[name] = _plain(value)
    if m.metrics.get("skipped"):
        meta["pass_through"] = True
    if m.notes:
        meta["notes"] = MetadataValue.md("\n".join(f"- {n}" for n in m.notes))
    # The files people open: the GLB, the true-size exports, the page with the 3D viewer.
    for name, label in (("asset.glb", "glb"), ("model.glb", "true_size_glb"), ("model.web.glb", "web_glb"),
                        ("model.usdz", "usdz"), ("viewer.html", "viewer")):
        if name in m.outputs:
            meta[label] = MetadataValue.path(str(stage_dir / name))
    preview = preview_markdown(stage_dir / BY_ID[m.stage].preview, f"{m.photo_key} · {m.stage}")
    if preview is not None:
        meta["preview"] = preview
    return meta


def check_metadata(check: QACheck) -> dict[str, Any]:
    return {"value": _plain(check.value) if check.value is not None else "not measured",
            "threshold": _plain(check.threshold), "severity": check.severity}
