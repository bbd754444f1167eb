"""The paper's stage-2 ablations on the synthetic scenes, with the oracle priors.

Stages 1a/1b run once per scene (under the low-passed 3D oracle); each row then re-runs only the
texture stage from the same DMTet output, so the rows differ in their stage-2 guidance alone, as
in the paper. Rows are overrides of ``texture.guidance`` — the same settings a user passes to
``morpheus3d run --set`` — and one configuration serves every scene (no per-scene tuning).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from benchmarks.oracle import OracleConfig
from benchmarks.scene_eval import EvalConfig, evaluate, mesh_output
from benchmarks.scene_runs import Schedule, photo_path, run_scene, schedule_store, stage_guards, stage_wall_s
from benchmarks.scenes import Scene

log = logging.getLogger("morpheus3d.bench")

G = "texture.guidance."


@dataclass(frozen=True)
class Row:
    name: str
    table: str  # "main", "k2d" or "r": which of the paper's tables the row belongs to
    overrides: tuple[str, ...]
    paper: str  # the paper's finding for this row, in words


ROWS: tuple[Row, ...] = (
    Row("base", "main", (f"{G}use_2d=false",), "3D prior only: lacks high-frequency detail (Fig. 7, 9)"),
    Row("full_pass_2d", "main", (f"{G}r=0.0",),
        "adding the 2D prior unfiltered brings colour deviation and is no better than Base (Fig. 7, 8)"),
    Row("high_pass_2d_sds", "main", (f"{G}mode_2d=sds",),
        "high-pass 2D without fine-tuning: better than Base, below VSD (Fig. 9)"),
    Row("ours", "main", (), "high-pass 2D prior with VSD: best on quality and consistency (Fig. 7, 9)"),
    Row("finetuned_3d", "main", (f"{G}mode_3d=vsd",),
        "VSD on the 3D prior: more high-frequency PSD but lower quality (artifacts, Fig. 11)"),
    *(Row(f"k2d={k}", "k2d", (f"{G}k2d={float(k)}",), paper) for k, paper in (
        (0, "k2D = 0 (no 2D prior) clearly worst"), (1, "≈ flat for 1 … 5"), (2, "≈ flat for 1 … 5"),
        (3, "≈ flat for 1 … 5 (the paper's choice)"), (4, "≈ flat for 1 … 5"), (5, "≈ flat for 1 … 5"))),
    *(Row(f"r={r:.1f}", "r", (f"{G}r={r}",), paper) for r, paper in (
        (0.0, "full pass: far worse (colour deviation)"), (0.2, "flat over the middle range"),
        (0.4, "flat over the middle range"), (0.6, "flat over the middle range (the paper's choice)"),
        (0.8, "flat over the middle range"), (1.0, "null pass (= no 2D prior): far worse (lacks detail)"))),
)

METRICS = ("novel_psnr", "detail_psnr", "novel_ssim", "hf_ratio", "colour_deviation", "chamfer", "fscore", "ref_psnr")


def run_ablations(scenes: list[Scene], schedule: Schedule, device: str, work: Path, eval_cfg: EvalConfig,
                  rows: tuple[Row, ...] = ROWS, oracle: OracleConfig | None = None,
                  on_record: Callable[[dict[str, Any]], None] | None = None) -> list[dict[str, Any]]:
    """One record per (scene, row): the row's metrics against ground truth, stage-2 time and guards.

    Also one ``stage1`` record per scene: the DMTet stage's own texture, before any stage-2 row.
    ``on_record`` sees each record as soon as it exists (to save it before the other rows end)."""
    store = schedule_store(work, schedule)
    dev = torch.device("cuda" if device == "cuda" else "cpu")
    base_cfg = schedule.config(device, ("texture.follow_plan=false",))
    records: list[dict[str, Any]] = []
    add = on_record or (lambda _r: None)
    for scene in scenes:
        photo = photo_path(scene, work / "photos")
        key = scene.name
        out = run_scene(scene, photo, store, base_cfg, schedule.label, key, until="dmtet", oracle=oracle)
        if out.error:
            records.append({"scene": scene.name, "row": "stage1", "error": out.error})
            add(records[-1])
            continue
        stage1 = evaluate(mesh_output(store, key, "dmtet", dev), scene, eval_cfg)
        records.append({"scene": scene.name, "row": "stage1", **stage1})
        add(records[-1])
        for row in rows:
            cfg = schedule.config(device, ("texture.follow_plan=false", *row.overrides))
            t0 = time.perf_counter()
            out = run_scene(scene, photo, store, cfg, schedule.label, key, until="texture", oracle=oracle)
            if out.error:
                records.append({"scene": scene.name, "row": row.name, "error": out.error})
                add(records[-1])
                continue
            metrics = evaluate(mesh_output(store, key, "texture", dev), scene, eval_cfg)
            records.append({"scene": scene.name, "row": row.name, **metrics,
                            "texture_wall_s": stage_wall_s(store, key, "texture"),
                            "guards": stage_guards(store, key, "texture"),
                            "bench_wall_s": round(time.perf_counter() - t0, 2)})
            add(records[-1])
            log.info("%s %-16s novel PSNR %.2f  colour dev %.4f  HF %.3f", scene.name, row.name,
                     metrics["novel_psnr"] or float("nan"), metrics["colour_deviation"] or float("nan"),
                     metrics["hf_ratio"] or float("nan"))
    return records


# The rows the findings need (``benchmarks/findings.py``); k2D = 0 and r = 1 switch the 2D term off
# (= base), r = 0 is the full pass and k2D = 3, r = 0.6 are ours, so those rows are not run twice.
FINDING_ROWS = ("base", "full_pass_2d", "high_pass_2d_sds", "ours", "finetuned_3d", "k2d=1", "k2d=2", "k2d=4",
                "k2d=5", "r=0.2", "r=0.4", "r=0.8")


def mean_by_row(records: list[dict[str, Any]]) -> dict[str, dict[str, float | None]]:
    """Each row's metrics averaged over the scenes where it finished."""
    out: dict[str, dict[str, float | None]] = {}
    names = [r["row"] for r in records]
    for name in dict.fromkeys(names):
        ok = [r for r in records if r["row"] == name and "error" not in r]
        out[name] = {"scenes": float(len(ok))}
        for m in METRICS:
            vals = [r[m] for r in ok if r.get(m) is not None]
            out[name][m] = sum(vals) / len(vals) if vals else None
    return out
