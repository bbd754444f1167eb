"""Prepare many photos: one reference folder each, a per-file outcome, never stop on a bad photo.

Folder names are the store's photo keys (safe characters only, unique within the batch). A
photo whose folder already holds a reference made with the same fingerprint as the pipeline's
reference stage would give it (file content, settings, code version) is left alone, so re-running
over a growing catalog only does the new photos, and changed settings redo them all.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TextIO

from assets_store.atomic import atomic_write_text
from assets_store.keys import assign_keys
from assets_store.manifest import Fingerprint
from assets_store.store import Store
from ops.config.presets import PipelineConfig
from ops.intake.errors import PreparationError
from ops.intake.plan import PlanConfig, plan_reference, read_plan
from ops.intake.prepare import PrepareConfig, prepare_reference, read_reference
from ops.intake.segment import Segmenter
from ops.pipeline.photo_run import PhotoRun
from ops.stages.reference import ReferenceStageConfig


@dataclass(frozen=True)
class Outcome:
    photo: Path
    folder: Path | None
    status: str  # "ok" | "warning" | "failed" | "up to date"
    method: str
    plan: str
    detail: str
    seconds: float


def folder_names(photos: Iterable[Path]) -> dict[Path, str]:
    """The store's photo key per photo (``assets_store.keys``): safe, unique and stable."""
    photos = list(photos)
    keys = assign_keys(p.name for p in photos)
    return {p: keys[p.name] for p in photos}


FINGERPRINT_FILE = "fingerprint.json"


def reference_fingerprint(photo: Path, cfg: PrepareConfig, plan_cfg: PlanConfig) -> Fingerprint:
    """The fingerprint the pipeline's reference stage gives this photo under these settings."""
    config = PipelineConfig(reference=ReferenceStageConfig(cfg, plan_cfg))
    run = PhotoRun(Path(photo), "prepare", Store(Path(photo).parent), config, "", None, None, None)
    return run.planned("reference").fingerprint


def _up_to_date(folder: Path, fp: Fingerprint) -> bool:
    try:
        recorded = json.loads((folder / FINGERPRINT_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return read_reference(folder) is not None and read_plan(folder) is not None and recorded == asdict(fp)


def prepare_one(photo: Path, folder: Path, cfg: PrepareConfig, plan_cfg: PlanConfig, segmenter: Segmenter,
                force: bool = False) -> Outcome:
    start = time.perf_counter()
    fp = reference_fingerprint(photo, cfg, plan_cfg)
    if not force and _up_to_date(folder, fp):
        return Outcome(photo, folder, "up to date", "-", "-", "reference already prepared from this file and "
                       "these settings", 0.0)
    try:
        info = prepare_reference(photo, folder, cfg, segmenter)
        plan = plan_reference(folder, plan_cfg)
        atomic_write_text(folder / FINGERPRINT_FILE, json.dumps(asdict(fp), sort_keys=True) + "\n")
    except PreparationError as exc:
        return Outcome(photo, None, "failed", "-", "-", f"{type(exc).__name__}: {exc.reason}. Fix: {exc.fix}",
                       time.perf_counter() - start)
    return Outcome(photo, folder, info.status, info.method, plan.summary(), "; ".join(info.warnings),
                   time.perf_counter() - start)


def prepare_many(photos: list[Path], out: Path, cfg: PrepareConfig, plan_cfg: PlanConfig, force: bool = False,
                 progress: Callable[[int, int, Outcome], None] | None = None) -> list[Outcome]:
    segmenter = Segmenter(cfg.segment)  # one rembg session for the whole batch
    names = folder_names(photos)
    outcomes = []
    for i, photo in enumerate(photos, 1):
        outcome = prepare_one(photo, out / names[photo], cfg, plan_cfg, segmenter, force)
        outcomes.append(outcome)
        if progress:
            progress(i, len(photos), outcome)
    return outcomes


def print_progress(i: int, n: int, outcome: Outcome, stream: TextIO | None = None) -> None:
    print(f"[{i}/{n}] {outcome.photo.name}: {outcome.status} ({outcome.seconds:.1f} s)", file=stream or sys.stderr,
          flush=True)


def failed_photos(outcomes: list[Outcome]) -> list[str]:
    """The file names of the photos that failed, in order (what the exit message names)."""
    return [str(o.photo.name) for o in outcomes if o.status == "failed"]


def format_table(outcomes: list[Outcome]) -> str:
    rows = [("PHOTO", "OUTCOME", "METHOD", "PLAN", "DETAIL")]
    rows += [(o.photo.name, o.status, o.method, o.plan, o.detail) for o in outcomes]
    widths = [max(len(r[c]) for r in rows) for c in range(4)]
    lines = ["  ".join(cell.ljust(w) for cell, w in zip(r[:4], widths, strict=True)) + "  " + r[4] for r in rows]
    counts = {s: sum(o.status == s for o in outcomes) for s in ("ok", "warning", "failed", "up to date")}
    lines.append(", ".join(f"{v} {k}" for k, v in counts.items() if v) or "no photos")
    return "\n".join(line.rstrip() for line in lines)
