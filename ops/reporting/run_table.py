"""The per-photo outcome table that ``morpheus3d run`` prints."""

from __future__ import annotations

from assets_store.store import Store
from ops.pipeline.photo_run import PhotoOutcome
from ops.pipeline.runner import uses_weight_free
from ops.stages.bake import ASSET_GLB


def steps_run(outcome: PhotoOutcome) -> str:
    """Steps the optimising stages reached of their schedules' steps; early stopping's saving."""
    done = [s.manifest.metrics for s in outcome.stages
            if s.manifest is not None and s.manifest.metrics.get("schedule_steps")]
    if not done:
        return "-"
    planned = sum(int(m["schedule_steps"]) for m in done)
    saved = sum(int(m.get("steps_saved", 0)) for m in done)
    return f"{planned - saved:,}/{planned:,}" + (f" (-{saved / planned:.0%})" if saved else "")


def qa_verdict(outcome: PhotoOutcome) -> str:
    """The QA stage's verdict (pass / warn / fail) with its count of failed checks; "-" when the
    run stopped before QA (``--until``, a failed stage). The reasons are in ``<photo>/qa/qa.json``."""
    decision = outcome.metric("qa", "verdict")
    if decision is None:
        return "-"
    failed = int(outcome.metric("qa", "failed_checks") or 0)
    return f"{decision} ({failed} check{'s' if failed != 1 else ''})" if failed else str(decision)


def format_run_table(outcomes: list[PhotoOutcome], store: Store) -> str:
    rows = [("PHOTO", "KEY", "OUTCOME", "QA", "STAGES", "TIME", "REF PSNR", "STEPS RUN", "RESULT")]
    for o in outcomes:
        stages = " ".join(f"{s.stage}={s.status}" for s in o.stages)
        psnr = o.metric("bake", "ref_psnr")
        result = o.error or str(store.stage_dir(o.key, "bake") / ASSET_GLB)
        rows.append((o.photo.name, o.key, o.status, qa_verdict(o), stages, f"{o.wall_s:.0f}s",
                     "-" if psnr is None else f"{psnr:.1f} dB", steps_run(o), result))
    n = len(rows[0]) - 1  # the last column is not padded
    widths = [max(len(r[c]) for r in rows) for c in range(n)]
    lines = ["  ".join(cell.ljust(w) for cell, w in zip(r[:n], widths, strict=True)) + "  " + r[n] for r in rows]
    counts = {s: sum(o.status == s for o in outcomes) for s in ("ok", "cached", "failed")}
    lines.append(", ".join(f"{v} {k}" for k, v in counts.items() if v) or "no photos")
    if any(o.metric("qa", "verdict") not in (None, "pass") for o in outcomes):
        lines.append("QA: warn / fail name their failed checks in <out>/<photo-key>/qa/qa.json "
                     "(`morpheus3d report` shows them)")
    if any(uses_weight_free(o) for o in outcomes):
        lines.append("NOTE: no diffusion weights installed — the weight-free proxy prior guided these assets "
                     "(see `morpheus3d doctor`).")
    return "\n".join(line.rstrip() for line in lines)
