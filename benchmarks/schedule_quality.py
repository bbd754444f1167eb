"""The ``fast`` preset against the paper's schedule: same asset, a quarter of the GPU time?

Reads the records of fixed-schedule runs of ``benchmarks/early_stop.py`` (``--variants fixed``,
stochastic oracle) of two schedules on the same scenes and pipeline seeds, e.g. ``paper/20`` and
``fast/20`` (both presets shortened alike, phases as fractions), and optionally the two presets'
``benchmarks/paper_speed.py`` results. Per scene: the exported GLB's novel-view PSNR, detail PSNR,
F-score and Chamfer distance of each schedule (mean over seeds), their paired difference (b − a,
seed by seed) and the seed spread (the larger of the two schedules' ranges over the seeds); a scene
is ``within`` when the mean difference is no worse than the spread. The bar: every scene within the
spread on GLB PSNR. The claim (``--expect``: 0, "b keeps a's quality", a flatness claim, the default;
1, "b beats a"; −1, "b is worse") is judged as the paper's findings are (``benchmarks/findings.py``),
on the seeds both schedules ran, and merged into ``findings.json``.

    python -m benchmarks.schedule_quality \\
        --records benchmarks/results/schedule_quality_h200_stochastic.records.jsonl \\
        --speed benchmarks/results/paper_speed_after_h200_paper.json \\
        benchmarks/results/paper_speed_after_h200_fast.json --name schedule_quality
"""

from __future__ import annotations

import argparse
import json
import shlex
import statistics
import sys
from pathlib import Path
from typing import Any

from benchmarks.early_stop import RESULTS
from benchmarks.findings import LOWER_IS_BETTER, Finding, findings_markdown, judge_all, write_findings
from benchmarks.quality import write_results
from benchmarks.schedule_curve import glb_rows

METRICS = ("novel_psnr", "detail_psnr", "fscore", "chamfer")


def compare(rows: list[dict[str, Any]], a: str, b: str) -> list[dict[str, Any]]:
    """Per scene and metric: both schedules' means, the paired difference b − a, the seed spread."""
    out = []
    for scene in dict.fromkeys(r["scene"] for r in rows):
        by = {(r["base"], r["seed"]): r for r in rows if r["scene"] == scene and r["base"] in (a, b)}
        seeds = sorted(s for s in {seed for _, seed in by} if (a, s) in by and (b, s) in by)
        if not seeds:
            continue
        row: dict[str, Any] = {"scene": scene, "seeds": seeds}
        for m in METRICS:
            va, vb = [by[(a, s)][m] for s in seeds], [by[(b, s)][m] for s in seeds]
            diffs = [y - x for x, y in zip(va, vb, strict=True)]
            spread = max(max(va) - min(va), max(vb) - min(vb))
            worse = -statistics.fmean(diffs) if m not in LOWER_IS_BETTER else statistics.fmean(diffs)
            row[m] = {"a": statistics.fmean(va), "b": statistics.fmean(vb), "delta": statistics.fmean(diffs),
                      "per_seed": diffs, "spread": spread, "within": worse <= spread}
        row["wall_s"] = {"a": statistics.fmean(by[(a, s)]["wall_s"] for s in seeds),
                         "b": statistics.fmean(by[(b, s)]["wall_s"] for s in seeds)}
        out.append(row)
    return out


def speed_summary(paths: list[Path]) -> list[dict[str, Any]]:
    """Minutes per object at each batch size of each ``paper_speed.py`` result."""
    out = []
    for p in paths:
        res = json.loads(p.read_text())
        for proj in res["projections"]:
            out.append({"preset": res["preset"], "file": p.name, "device": res["device"], "date": res["date"],
                        "batch": proj["batch"], "min_per_object": proj["min_per_object"],
                        **{f"{s}_min": proj[f"{s}_min"] for s in ("nerf", "dmtet", "texture")}})
    return out


def markdown(table: list[dict[str, Any]], a: str, b: str, speed: list[dict[str, Any]]) -> str:
    lines = ["| scene | seeds | GLB PSNR " + a + " | " + b + " | Δ (per seed) | spread | within |"
             " detail PSNR Δ | F-score " + a + " → " + b + " | Chamfer Δ | wall s (" + a + " / " + b + ") |",
             "|---|---:|---:|---:|---|---:|---|---:|---|---:|---|"]
    for r in table:
        p, d, f, c = r["novel_psnr"], r["detail_psnr"], r["fscore"], r["chamfer"]
        per = ", ".join(f"{x:+.2f}" for x in p["per_seed"])
        lines.append(f"| {r['scene']} | {len(r['seeds'])} | {p['a']:.2f} | {p['b']:.2f} | {p['delta']:+.2f} ({per}) | "
                     f"{p['spread']:.2f} | {'yes' if p['within'] else '**no**'} | {d['delta']:+.2f} "
                     f"({'within' if d['within'] else 'outside'} {d['spread']:.2f}) | {f['a']:.3f} → {f['b']:.3f} | "
                     f"{c['delta']:+.4f} | {r['wall_s']['a']:.0f} / {r['wall_s']['b']:.0f} |")
    ok = sum(r["novel_psnr"]["within"] for r in table)
    lines += ["", f"GLB PSNR within the seed spread on **{ok} of {len(table)}** scenes (Δ = {b} − {a})."]
    if speed:
        lines += ["", "GPU time per object (``benchmarks/paper_speed.py``, the full schedules extrapolated from "
                  "timed steps):",
                  "", "| preset | file | device | batch | NeRF min | DMTet min | texture min | **min / object** |",
                  "|---|---|---|---:|---:|---:|---:|---:|"]
        lines += [f"| {s['preset']} | {s['file']} | {s['device']} | {s['batch']} | {s['nerf_min']} | "
                  f"{s['dmtet_min']} | {s['texture_min']} | **{s['min_per_object']}** |" for s in speed]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--records", type=Path, nargs="+", required=True, help="early_stop record files (JSON lines)")
    ap.add_argument("--a", default="paper/20", help="the reference schedule")
    ap.add_argument("--b", default="fast/20", help="the schedule judged against it")
    ap.add_argument("--expect", type=int, choices=(-1, 0, 1), default=0,
                    help="the claim judged: 0, b keeps a's quality (a flatness claim); 1, b beats a; -1, b is worse")
    ap.add_argument("--source", default="issue: fewer, fuller steps", help="where the claim comes from")
    ap.add_argument("--speed", type=Path, nargs="*", default=[], help="paper_speed.py JSON results of both presets")
    ap.add_argument("--name", default="schedule_quality")
    ap.add_argument("--results", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    records = [json.loads(line) for f in args.records for line in f.read_text().splitlines() if line]
    rows = [r for r in glb_rows(records) if r["oracle"] == "stochastic"]
    table = compare(rows, args.a, args.b)
    if not table:
        print(f"no scene ran both {args.a} and {args.b} on the same seed", file=sys.stderr)
        return 1
    machines = sorted({r["machine"] for r in records if r.get("machine")})
    size = f"{args.a} vs {args.b}, stochastic oracle, {machines[0].split(',')[0]}"
    both = [r for r in rows if r["scene"] in {t["scene"] for t in table}]
    # The seeds both schedules ran on every compared scene (a longer schedule may have fewer).
    seeds = sorted(set.intersection(*(set(t["seeds"]) for t in table)))
    by_seed = {s: [r for r in both if r["seed"] == s] for s in seeds}
    claim = {0: "keeps {a}'s quality", 1: "beats {a}", -1: "is worse than {a}"}[args.expect].format(a=args.a)
    finding = Finding(f"{args.b} {claim}", (args.a,), (args.b,), args.expect, args.source)
    judged = judge_all(by_seed, size, (finding,), key="base")
    if judged:
        write_findings(args.results, judged)
    speed = speed_summary(args.speed)
    write_results(args.results, args.name, {
        "title": f"{args.b} against {args.a}", "machine": "; ".join(machines), "wall_s": 0.0,
        "date": max(r["date"] for r in records if r.get("date")), "from_records": True,
        "command": "python -m benchmarks.schedule_quality " + shlex.join(argv if argv is not None else sys.argv[1:]),
        "rows": table, "speed": speed, "findings": judged, "about": __doc__.split("\n\n")[1].replace("\n", " ")},
        markdown(table, args.a, args.b, speed) + ("\n" + findings_markdown(judged) if judged else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
