"""What the bake loses: the GLB against the texture stage's own output on the benchmark scenes.

The texture stage's output is the DMTet mesh coloured by its texture field, queried per pixel; the
GLB is that field baked into a square texture on a UV-unwrapped copy of the mesh (floaters dropped,
decimated to the plan's face budget). This re-runs only the bake stage of finished runs of
``benchmarks/early_stop.py`` (the stage fingerprints keep every other stage cached) once per
variant of the bake's settings, and scores each GLB and the texture stage against the ground truth
as the rest of the benchmark does; the gap is GLB − texture novel-view PSNR.

    python -m benchmarks.bake_gap --device cuda --work /tmp/es --records early_stop_curve_h100.records.jsonl
    python -m benchmarks.bake_gap --from-records benchmarks/results/bake_gap_h100.records.jsonl --name bake_gap_h100
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import statistics
import sys
import time
import traceback
from concurrent.futures import ProcessPoolExecutor, as_completed
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import torch

from benchmarks.early_stop import BASES, RESULTS, STOPPING, oracle_work, variant_schedule
from benchmarks.oracle import OracleConfig
from benchmarks.quality import SIZES, machine, worker_init, write_results
from benchmarks.scene_eval import EvalConfig, Reconstruction, evaluate, glb_output, mesh_output, novel_cameras
from benchmarks.scene_runs import photo_path, run_scene, schedule_store, stage_wall_s
from benchmarks.scenes import make_scenes
from morpheus_core.metrics.image import psnr
from ops.stages.bake import ASSET_GLB

# One setting changed at a time from the preset's (the paper's 1024² map at the plan's face budget).
VARIANTS: dict[str, tuple[str, ...]] = {
    "preset": (),  # the paper preset: 1024²
    "2048²": ("bake.map.texture_size=2048",),
    "4096²": ("bake.map.texture_size=4096",),
    "2048² undecimated": ("bake.map.texture_size=2048", "bake.max_faces=1000000"),
}
METRICS = ("novel_psnr", "detail_psnr")


def fidelity_psnr(glb: Reconstruction, texture: Reconstruction, cfg: EvalConfig) -> float:
    """PSNR of the GLB's novel views against the texture stage's own (not the truth): what the bake
    keeps of the field, apart from whether the field was right. Against the truth a bake can score
    higher than its field when its texels average the field's noise away."""
    cams, r = novel_cameras(cfg), cfg.resolution
    with torch.no_grad():
        a, b = glb.render(cams, r).rgb_chw().float().cpu(), texture.render(cams, r).rgb_chw().float().cpu()
    return statistics.fmean(psnr(a[i], b[i]) for i in range(len(cams)))


def bake_cell(record: dict[str, Any], variants: dict[str, tuple[str, ...]], device: str, work: Path,
              log: Path) -> int:
    """Every variant's bake of one finished (schedule, scene, seed) run, each scored and appended to
    ``log`` as it finishes; returns how many were written."""
    oracle = OracleConfig.named(record.get("oracle", "stochastic"))
    schedule = variant_schedule(BASES[record["base"]], record["seed"], bool(record["early_stop"]),
                                record.get("stop_rule", "reference"), tuple(record.get("stop_stages", STOPPING)))
    root = oracle_work(work, oracle)
    store = schedule_store(root, schedule)
    scene = make_scenes(0, (record["scene"],))[0]
    if store.read_manifest(scene.name, "texture") is None:  # a run of another machine: nothing here to re-bake
        return 0
    dev = torch.device("cuda" if device == "cuda" else "cpu")
    eval_cfg = SIZES["gpu" if device == "cuda" else "cpu"].eval
    texture_output = mesh_output(store, scene.name, "texture", dev)
    texture = evaluate(texture_output, scene, eval_cfg)
    written = 0
    for name, overrides in variants.items():
        cfg = schedule.config(device, ("texture.follow_plan=false", *overrides))
        out = run_scene(scene, photo_path(scene, root / "photos"), store, cfg, schedule.label, scene.name,
                        until="bake", oracle=oracle)
        if out.error:
            print(f"{schedule.label} {scene.name} {name}: {out.error}", file=sys.stderr, flush=True)
            continue
        glb_out = glb_output(store.stage_dir(scene.name, "bake") / ASSET_GLB, dev)
        glb = evaluate(glb_out, scene, eval_cfg)
        bake = store.read_manifest(scene.name, "bake")
        rec = {"base": record["base"], "scene": scene.name, "seed": record["seed"], "oracle": oracle.kind,
               "variant": name, "overrides": list(overrides),
               **{f"texture_{m}": texture[m] for m in METRICS}, **{f"glb_{m}": glb[m] for m in METRICS},
               "gap_psnr": glb["novel_psnr"] - texture["novel_psnr"],
               "gap_detail_psnr": glb["detail_psnr"] - texture["detail_psnr"],
               "fidelity_psnr": fidelity_psnr(glb_out, texture_output, eval_cfg),
               "faces": bake.metrics.get("faces"), "source_faces": bake.metrics.get("source_faces"),
               "uv_coverage": bake.metrics.get("uv_coverage"), "bake_s": stage_wall_s(store, scene.name, "bake"),
               "machine": machine(device), "date": datetime.now(timezone.utc).strftime("%Y-%m-%d")}
        with log.open("a", encoding="utf-8") as fh:
            fh.write(json.dumps(rec, default=str) + "\n")
        written += 1
    return written


def _mean_of(records: list[dict[str, Any]], key: str) -> float | None:
    """The mean of ``key`` over the records that have it (older records lack the fidelity PSNR)."""
    values = [r[key] for r in records if r.get(key) is not None]
    return statistics.fmean(values) if values else None


def summarise(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per variant: the mean gap over runs, its worst scene, and how many runs are within 0.3 dB."""
    rows = []
    for variant in dict.fromkeys(r["variant"] for r in records):
        mine = [r for r in records if r["variant"] == variant]
        by_scene = {s: statistics.fmean(r["gap_psnr"] for r in mine if r["scene"] == s)
                    for s in dict.fromkeys(r["scene"] for r in mine)}
        worst = min(by_scene, key=by_scene.__getitem__)
        rows.append({"variant": variant, "runs": len(mine),
                     "gap_psnr": statistics.fmean(r["gap_psnr"] for r in mine),
                     "gap_detail_psnr": statistics.fmean(r["gap_detail_psnr"] for r in mine),
                     "worst_scene": worst, "worst_gap_psnr": by_scene[worst],
                     "within_0.3": sum(r["gap_psnr"] >= -0.3 for r in mine),
                     "fidelity_psnr": _mean_of(mine, "fidelity_psnr"),
                     "per_scene": by_scene, "bake_s": statistics.fmean(r["bake_s"] for r in mine),
                     "faces": statistics.fmean(r["faces"] for r in mine)})
    return rows


def markdown(rows: list[dict[str, Any]]) -> str:
    scenes = list(dict.fromkeys(s for r in rows for s in r["per_scene"]))
    lines = ["| bake | runs | Δ PSNR GLB − texture (dB) | Δ detail PSNR (dB) | runs within 0.3 dB | "
             + " | ".join(f"Δ {s}" for s in scenes) + " | GLB vs texture stage PSNR | faces | bake s |",
             "|---|---:|---:|---:|---:|" + "---:|" * len(scenes) + "---:|---:|---:|"]
    for r in rows:
        per = " | ".join(f"{r['per_scene'][s]:+.2f}" if s in r["per_scene"] else "–" for s in scenes)
        fidelity = "–" if r.get("fidelity_psnr") is None else f"{r['fidelity_psnr']:.2f}"
        lines.append(f"| {r['variant']} | {r['runs']} | {r['gap_psnr']:+.2f} | {r['gap_detail_psnr']:+.2f} | "
                     f"{r['within_0.3']}/{r['runs']} | {per} | {fidelity} | {r['faces']:.0f} | {r['bake_s']:.1f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--records", type=Path, help="early_stop records (JSON lines) of the finished runs to re-bake")
    ap.add_argument("--work", type=Path, default=Path("outputs/early_stop"), help="early_stop's --work")
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--variants", default=",".join(VARIANTS), help=f"comma-separated, of {list(VARIANTS)}")
    ap.add_argument("--jobs", type=int, default=1, help="runs re-baked at once, each in its own process")
    ap.add_argument("--results", type=Path, default=RESULTS)
    ap.add_argument("--name", default="bake_gap")
    ap.add_argument("--from-records", type=Path, nargs="*", default=None,
                    help="summarise these bake_gap record files instead of baking")
    args = ap.parse_args(argv)
    start = time.perf_counter()
    if args.from_records is None:
        if args.records is None:
            ap.error("--records (the early_stop runs to re-bake) or --from-records is required")
        wanted = [v for v in args.variants.split(",") if v]
        unknown = [v for v in wanted if v not in VARIANTS]
        if unknown:
            ap.error(f"unknown variant(s) {unknown}; choose from {list(VARIANTS)}")
        variants = {v: VARIANTS[v] for v in wanted}
        runs = [json.loads(line) for line in args.records.read_text().splitlines() if line]
        log = args.results / f"{args.name}.records.jsonl"
        args.results.mkdir(parents=True, exist_ok=True)
        calls = [(r, variants, args.device, args.work, log) for r in runs if not r["early_stop"]]
        with ProcessPoolExecutor(max(1, args.jobs), mp_context=multiprocessing.get_context("spawn"),
                                 initializer=worker_init, initargs=(max(1, torch.get_num_threads() // args.jobs),)
                                 ) as pool:
            futures = {pool.submit(bake_cell, *c): c[0] for c in calls}
            for future in as_completed(futures):
                try:
                    future.result()
                except Exception:  # one broken run must not cost the others' records
                    r = futures[future]
                    print(f"FAILED {r['base']} {r['scene']} s{r['seed']}:\n{traceback.format_exc()}",
                          file=sys.stderr, flush=True)
        files = [log]
    else:
        files = args.from_records
    records = [json.loads(line) for f in files if f.is_file() for line in f.read_text().splitlines() if line]
    if not records:
        print("no bake records", file=sys.stderr)
        return 1
    rows = summarise(records)
    write_results(args.results, args.name, {
        "title": "What the bake loses: GLB against the texture stage", "machine": records[0]["machine"],
        "date": records[-1]["date"], "wall_s": time.perf_counter() - start,
        "command": "python -m benchmarks.bake_gap " + " ".join(argv if argv is not None else sys.argv[1:]),
        "rows": rows, "about": __doc__.split("\n\n")[1].replace("\n", " ")}, markdown(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
