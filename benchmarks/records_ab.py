"""Two record files of ``benchmarks/early_stop.py`` compared: A (the reference) against B (a change).

Cells are paired on (schedule, scene, seed, early stopping). Per scene and over all scenes: the GLB
metrics' mean ± sd over seeds for A and B, the paired difference B − A of the GLB PSNR, and whether
B's mean lies inside A's min–max over seeds (the issue's "within the seed spread"), for PSNR,
Chamfer and F-score; also the paired differences after the NeRF and DMTet stages.

    python -m benchmarks.records_ab A.records.jsonl B.records.jsonl --name heads_quality_h200 \\
        --title "Fused field heads (TF32) against the modules (fp32)"
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path
from typing import Any

from benchmarks.early_stop import METRICS, RESULTS, _glb, _mean_sd
from benchmarks.quality import _write


def _key(rec: dict[str, Any]) -> tuple[str, str, int, bool]:
    return rec["base"], rec["scene"], rec["seed"], rec["early_stop"]


def _stage(rec: dict[str, Any], stage: str) -> dict[str, float]:
    return next(p for p in rec["points"] if p["stage"] == stage)


def compare(a: list[dict[str, Any]], b: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per scene and one over all scenes, from the cells both files finished."""
    by_a = {_key(r): r for r in a if "points" in r}
    pairs = [(by_a[_key(r)], r) for r in b if "points" in r and _key(r) in by_a]
    if not pairs:
        return []
    rows = []
    scenes = list(dict.fromkeys(ra["scene"] for ra, _ in pairs))
    for scene in [*scenes, "all scenes"]:
        pick = [(ra, rb) for ra, rb in pairs if scene == "all scenes" or ra["scene"] == scene]
        seeds = sorted({ra["seed"] for ra, _ in pick})
        row: dict[str, Any] = {"scene": scene, "pairs": len(pick), "seeds": seeds}
        for tag, side in (("a", 0), ("b", 1)):
            for m in METRICS:  # over scenes: the per-seed mean, so the spread is the seeds' spread
                per_seed = [statistics.fmean(_glb(p[side])[m] for p in pick if p[0]["seed"] == s) for s in seeds]
                row[f"{tag}_{m}"], row[f"{tag}_{m}_sd"] = _mean_sd(per_seed)
                row[f"{tag}_{m}_range"] = (min(per_seed), max(per_seed))
        for m in METRICS:
            lo, hi = row[f"a_{m}_range"]
            row[f"{m}_within_spread"] = lo <= row[f"b_{m}"] <= hi
        row["delta_psnr"], row["delta_psnr_sd"] = _mean_sd([_glb(rb)["novel_psnr"] - _glb(ra)["novel_psnr"]
                                                            for ra, rb in pick])
        for stage in ("nerf", "dmtet"):
            row[f"delta_{stage}_psnr"], _ = _mean_sd([_stage(rb, stage)["novel_psnr"] - _stage(ra, stage)["novel_psnr"]
                                                      for ra, rb in pick])
        row["a_wall_s"] = statistics.fmean(_glb(ra)["wall_s"] for ra, _ in pick)
        row["b_wall_s"] = statistics.fmean(_glb(rb)["wall_s"] for _, rb in pick)
        rows.append(row)
    return rows


def markdown(rows: list[dict[str, Any]]) -> str:
    lines = ["| scene | GLB PSNR A (dB) | GLB PSNR B (dB) | paired Δ B − A (dB) | Δ NeRF / DMTet PSNR (dB) | "
             "Chamfer A → B | F-score A → B | B inside A's seed range (PSNR/Chamfer/F) |",
             "|---|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        within = "/".join("yes" if r[f"{m}_within_spread"] else "no" for m in METRICS)
        name = f"**{r['scene']}**" if r["scene"] == "all scenes" else r["scene"]
        lines.append(f"| {name} | {r['a_novel_psnr']:.2f} ± {r['a_novel_psnr_sd']:.2f} | "
                     f"{r['b_novel_psnr']:.2f} ± {r['b_novel_psnr_sd']:.2f} | {r['delta_psnr']:+.2f} ± "
                     f"{r['delta_psnr_sd']:.2f} (n={r['pairs']}) | {r['delta_nerf_psnr']:+.2f} / "
                     f"{r['delta_dmtet_psnr']:+.2f} | {r['a_chamfer']:.4f} → {r['b_chamfer']:.4f} | "
                     f"{r['a_fscore']:.3f} → {r['b_fscore']:.3f} | {within} |")
    return ("\n".join(lines) + "\n\n± is the standard deviation over the pipeline seeds (over scenes: of the "
            "per-seed means). Paired Δ: the same (scene, seed) cell in B minus A, mean ± sd over the pairs.\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("a", type=Path, help="reference records (JSON lines)")
    ap.add_argument("b", type=Path, help="records of the change")
    ap.add_argument("--name", required=True, help="results file stem")
    ap.add_argument("--title", default="Two record files compared")
    ap.add_argument("--about", default="", help="what A and B are, for the Markdown")
    ap.add_argument("--results", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    read = [[json.loads(line) for line in f.read_text().splitlines() if line] for f in (args.a, args.b)]
    rows = compare(*read)
    if not rows:
        raise SystemExit(f"no (schedule, scene, seed, variant) cell finished in both {args.a} and {args.b}")
    payload = {"title": args.title, "machine": read[1][0]["machine"], "date": read[1][0]["date"],
               "command": "python -m benchmarks.records_ab " + " ".join(argv if argv is not None else sys.argv[1:]),
               "wall_s": 0.0, "about": args.about or f"A: `{args.a.name}`; B: `{args.b.name}`.", "rows": rows}
    _write(args.results, args.name, payload, markdown(rows))
    print(markdown(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
