"""Error against schedule length: where each scene's curve flattens, and how far the oracle is from saturation.

Reads the records of fixed-schedule runs of ``benchmarks/early_stop.py`` (``--variants fixed``; one
file per oracle, ``--oracle``) at several lengths of one preset, e.g. the paper's schedule at 1/40,
1/20 and 1/10 of its steps, several pipeline seeds each. Per scene and schedule: the exported GLB's
novel-view and detail PSNR (mean and range over the seeds) and each stage's PSNR; per scene, the
schedule after which the curve is flat (every longer schedule's mean within the seed spread of
it) or ``still rising``; the stochastic oracle against the noise-free one where both ran; and the
finding "more steps pay" (the longest schedule against the shortest), judged as the other
findings are and merged into ``findings.json``.

    python -m benchmarks.schedule_curve --records benchmarks/results/schedule_curve_h100_stochastic.records.jsonl \\
        benchmarks/results/schedule_curve_h100_noise-free.records.jsonl --name schedule_curve_h100
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path
from typing import Any

from benchmarks.early_stop import BASES, RESULTS
from benchmarks.error_time import POINTS
from benchmarks.findings import Finding, findings_markdown, judge_all, write_findings
from benchmarks.quality import write_results

METRICS = ("novel_psnr", "detail_psnr", "chamfer", "fscore")


def _steps(label: str) -> int:
    steps = BASES[label].steps
    return sum(steps) if steps is not None else 0


def glb_rows(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One flat row per run: its schedule, scene, seed, oracle, the GLB's metrics and each stage's PSNR."""
    rows = []
    for r in records:
        if r.get("early_stop") or "points" not in r:
            continue
        points = {p["stage"]: p for p in r["points"]}
        rows.append({"base": r["base"], "scene": r["scene"], "seed": r["seed"],
                     "oracle": r.get("oracle", "noise-free"), "wall_s": points[POINTS[-1]]["wall_s"],
                     **{m: points[POINTS[-1]][m] for m in METRICS},
                     **{f"{stage}_psnr": points[stage]["novel_psnr"] for stage in POINTS}})
    return rows


def curve(rows: list[dict[str, Any]], oracle: str) -> dict[str, list[dict[str, Any]]]:
    """Per scene, the schedules in order of length: mean and min–max over seeds of each metric."""
    out: dict[str, list[dict[str, Any]]] = {}
    mine = [r for r in rows if r["oracle"] == oracle]
    for scene in dict.fromkeys(r["scene"] for r in mine):
        points = []
        for base in sorted({r["base"] for r in mine if r["scene"] == scene}, key=_steps):
            runs = [r for r in mine if r["scene"] == scene and r["base"] == base]
            point: dict[str, Any] = {"base": base, "steps": _steps(base), "seeds": sorted(r["seed"] for r in runs)}
            for m in (*METRICS, *(f"{s}_psnr" for s in POINTS), "wall_s"):
                values = [r[m] for r in runs]
                point[m] = statistics.fmean(values)
                point[f"{m}_range"] = max(values) - min(values)
            points.append(point)
        out[scene] = points
    return out


def flattens(points: list[dict[str, Any]], metric: str = "novel_psnr") -> dict[str, Any]:
    """Where the curve is flat: the first schedule whose every longer schedule lies within the seed
    spread (the largest min–max over seeds on the curve, at least one point with two seeds) of it.
    ``moves``: the last point differs from the first by more than that spread."""
    spread = max((p[f"{metric}_range"] for p in points if len(p["seeds"]) > 1), default=float("nan"))
    first, last = points[0][metric], points[-1][metric]
    flat_from = "still rising"
    for i, p in enumerate(points[:-1]):
        if all(abs(q[metric] - p[metric]) <= spread for q in points[i + 1:]):
            flat_from = p["base"]
            break
    return {"spread": spread, "first_to_last": last - first, "moves": abs(last - first) > spread,
            "flat_from": flat_from if len(points) > 1 else "one point"}


def markdown(curves: dict[str, dict[str, list[dict[str, Any]]]], rows: list[dict[str, Any]]) -> str:
    lines = ["| oracle | scene | schedule (steps) | seeds | GLB PSNR (dB) | detail PSNR | NeRF / DMTet / texture "
             "PSNR | GLB − texture | Chamfer | F-score | wall s |",
             "|---|---|---|---|---:|---:|---|---:|---:|---:|---:|"]
    for oracle, per_scene in curves.items():
        for scene, points in per_scene.items():
            for p in points:
                stages = " / ".join(f"{p[f'{s}_psnr']:.2f}" for s in POINTS[:-1])
                lines.append(f"| {oracle} | {scene} | {p['base']} ({p['steps']}) | {len(p['seeds'])} | "
                             f"{p['novel_psnr']:.2f} ± {p['novel_psnr_range'] / 2:.2f} | {p['detail_psnr']:.2f} | "
                             f"{stages} | {p['bake_psnr'] - p['texture_psnr']:+.2f} | {p['chamfer']:.4f} | "
                             f"{p['fscore']:.3f} | {p['wall_s']:.0f} |")
    lines += ["", "± is half the range over the seeds. Where each curve flattens (GLB novel-view PSNR):", "",
              "| oracle | scene | first → last point (dB) | seed spread (dB) | moves more than the spread | "
              "flat from |", "|---|---|---:|---:|---|---|"]
    for oracle, per_scene in curves.items():
        for scene, points in per_scene.items():
            f = flattens(points)
            lines.append(f"| {oracle} | {scene} | {f['first_to_last']:+.2f} | {f['spread']:.2f} | "
                         f"{'yes' if f['moves'] else 'no'} | {f['flat_from']} |")
    both = _oracle_pairs(rows)
    if both:
        lines += ["", "Stochastic against noise-free oracle, same schedule, scene and seed (GLB novel-view PSNR):", "",
                  "| schedule | scene | seed | noise-free (dB) | stochastic (dB) | Δ |", "|---|---|---|---:|---:|---:|"]
        lines += [f"| {b} | {s} | {seed} | {nf:.2f} | {st:.2f} | {st - nf:+.2f} |" for b, s, seed, nf, st in both]
        for base in sorted({x[0] for x in both}, key=_steps):  # the mean over scenes, per schedule
            nf, st = zip(*[(x[3], x[4]) for x in both if x[0] == base], strict=True)
            lines.append(f"| **{base}, all scenes** | | | {statistics.fmean(nf):.2f} | {statistics.fmean(st):.2f} | "
                         f"{statistics.fmean(st) - statistics.fmean(nf):+.2f} |")
    return "\n".join(lines) + "\n"


def _oracle_pairs(rows: list[dict[str, Any]]) -> list[tuple[str, str, int, float, float]]:
    by = {(r["oracle"], r["base"], r["scene"], r["seed"]): r["novel_psnr"] for r in rows}
    return sorted((b, s, seed, v, by[("stochastic", b, s, seed)]) for (o, b, s, seed), v in by.items()
                  if o == "noise-free" and ("stochastic", b, s, seed) in by)


def more_steps_finding(rows: list[dict[str, Any]], size: str) -> list[dict[str, Any]]:
    """"More steps pay": the longest schedule against the shortest, stochastic oracle, scenes run at both."""
    mine = [r for r in rows if r["oracle"] == "stochastic"]
    bases = sorted({r["base"] for r in mine}, key=_steps)
    if len(bases) < 2:
        return []
    finding = Finding(f"more steps pay ({bases[-1]} beats {bases[0]})", (bases[0],), (bases[-1],), +1,
                      "§5: 10k + 5k + 5k steps")
    by_seed = {s: [r for r in mine if r["seed"] == s] for s in sorted({r["seed"] for r in mine})}
    # Paired by seed: a seed run at only one of the two lengths says nothing about the difference.
    by_seed = {s: rs for s, rs in by_seed.items() if {bases[0], bases[-1]} <= {r["base"] for r in rs}}
    return judge_all(by_seed, size, (finding,), key="base")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--records", type=Path, nargs="+", required=True, help="early_stop record files (JSON lines)")
    ap.add_argument("--preset", default="paper", help="the preset whose shortened schedules make the curve "
                    "(records of other presets in the same files, e.g. fast/20, are left out)")
    ap.add_argument("--name", default="schedule_curve")
    ap.add_argument("--results", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    records = [json.loads(line) for f in args.records for line in f.read_text().splitlines() if line]
    rows = [r for r in glb_rows(records) if r["base"].split("/")[0] == args.preset]
    if not rows:
        print("no fixed-schedule records with points", file=sys.stderr)
        return 1
    curves = {o: curve(rows, o) for o in ("stochastic", "noise-free") if any(r["oracle"] == o for r in rows)}
    machines = sorted({r["machine"] for r in records if r.get("machine")})
    size = (f"{' → '.join(sorted({r['base'] for r in rows}, key=_steps))}, stochastic oracle, "
            f"{machines[0].split(',')[0]}")
    judged = more_steps_finding(rows, size)
    if judged:  # one "more steps pay" row per preset, oracle and machine: over the schedules run so far
        machine = machines[0].split(",")[0]
        write_findings(args.results, judged, lambda r: (
            r["finding"].startswith("more steps pay") and r["size"].startswith(f"{args.preset}/")
            and r["size"].endswith(f"stochastic oracle, {machine}")))
    flat = {o: {s: flattens(p) for s, p in c.items()} for o, c in curves.items()}
    write_results(args.results, args.name, {
        "title": "Error against schedule length", "machine": "; ".join(machines), "wall_s": 0.0,
        "date": max(r["date"] for r in records if r.get("date")), "from_records": True,
        "command": "python -m benchmarks.schedule_curve " + " ".join(argv if argv is not None else sys.argv[1:]),
        "rows": rows, "curves": curves, "flattens": flat, "findings": judged,
        "about": __doc__.split("\n\n")[1].replace("\n", " ")},
        markdown(curves, rows) + ("\n" + findings_markdown(judged) if judged else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
