"""Early stopping on and off: steps and minutes saved per scene, and the GLB metrics against the seed spread.

Each (schedule, scene, seed) runs the whole pipeline twice with the oracle priors, once with the
fixed schedule (``*.loop.early_stop=false``, the default) and once with early stopping in the stages
the title names (by default the NeRF and DMTet stages, ``--stop-stages``; the texture stage stays on
its schedule: ``early_stop_texture_h200.md`` shows why) under its rule (``--stop-rule``), and scores
every stage's output as ``benchmarks/error_time.py`` does. A difference counts as within
the spread when the early-stopping mean over seeds lies within the fixed path's min–max over seeds.
The stages log their reference-view PSNR about 40 times per stage here (``log_every`` = steps/40),
as the presets do (100–200 rows per stage), so the rule sees a real curve.

    python -m benchmarks.early_stop --device cuda --jobs 8 --schedules paper/10 --scenes mug,box,bottle,chair \
        --seeds 0,1
    python -m benchmarks.early_stop --schedules draft --scenes mug --seeds 0 --name early_stop_smoke   # CPU smoke
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import statistics
import sys
import time
import traceback
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import replace
from datetime import datetime, timezone
from functools import partial
from pathlib import Path
from typing import Any

import torch

from benchmarks.error_time import POINTS, run_error_time
from benchmarks.oracle import ORACLE_KINDS, OracleConfig
from benchmarks.quality import SIZES, machine, worker_init, write_results
from benchmarks.scene_eval import EvalConfig
from benchmarks.scene_runs import Schedule, photo_path, schedule_store
from benchmarks.scenes import SCENE_NAMES, make_scenes

RESULTS = Path(__file__).parent / "results"
OPTIMISING = ("nerf", "dmtet", "texture")
STOPPING = ("nerf", "dmtet")
# paper/10: the paper's schedule at a tenth of its steps, long enough for the NeRF stage to run 40 % of
# its steps with all hash-grid levels on (the rule may stop it only then) and short enough for one device call.
# paper/40 and paper/20 are the shorter points of the schedule curve (``benchmarks/schedule_curve.py``);
# fast/20 is the fast preset shortened as paper/20 is (``benchmarks/schedule_quality.py`` compares them).
# The CPU benchmark's schedule with half its steps, each stage's first half rendering four views at half
# size: the fast preset's recipe at the CPU size (``benchmarks/schedule_quality.py`` compares it with bench-cpu).
_BENCH_CPU_HALF_PHASED = Schedule("bench-cpu/2-phased", "draft", steps=(75, 40, 75), overrides=(
    "texture.resolution=128", *(f'{s}.phases=[{{"until": 0.5, "resolution": {r}, "n_views": 4}}]'
                                for s, r in (("nerf", 24), ("dmtet", 48), ("texture", 64)))))
BASES = {s.label: s for s in (SIZES["cpu"].ablation, *SIZES["gpu"].timing,
                              Schedule("paper/40", "paper", steps=(250, 125, 125)),
                              Schedule("paper/10", "paper", steps=(1000, 500, 500)),
                              Schedule("fast/20", "fast", steps=(125, 62, 62)),
                              _BENCH_CPU_HALF_PHASED)}
METRICS = ("novel_psnr", "chamfer", "fscore")


STOP_RULES = ("sides", "reference")
"""How the early runs stop: on the reference view once the held-out side views have settled (the default rule),
or on the reference view alone (``*.loop.early_stop_watch_sides=false``, the rule of the earlier results)."""


def variant_schedule(base: Schedule, seed: int, early: bool, rule: str = "sides",
                     stages: tuple[str, ...] = STOPPING) -> Schedule:
    """The run of one cell: the fixed schedule, or early stopping in ``stages`` under ``rule``. Early runs under
    the reference rule in the default stages keep the store label they had before the side views existed."""
    cfg = base.config("cpu")
    logs = tuple(f"{s}.loop.log_every={max(1, getattr(cfg, s).loop.steps // 40)}" for s in OPTIMISING)
    stops = tuple(f"{s}.loop.early_stop={str(early and s in stages).lower()}" for s in OPTIMISING)
    sides = (f"*.loop.early_stop_watch_sides={str(rule == 'sides').lower()}",) if early else ()
    kind = "fixed"
    if early:
        kind = "early" + ("-sides" if rule == "sides" else "") + ("" if stages == STOPPING else "-" + "+".join(stages))
    label = f"{base.label.replace('/', '-')}.{kind}.s{seed}"
    return replace(base, label=label, overrides=(*base.overrides, *logs, *stops, *sides, f"seed={seed}"))


def _steps(work: Path, schedule: Schedule, scene: str) -> dict[str, dict[str, int]]:
    store = schedule_store(work, schedule)
    out = {}
    for stage in OPTIMISING:
        m = store.read_manifest(scene, stage)
        if m is not None:
            out[stage] = {"run": int(m.metrics.get("steps_run", 0)), "saved": int(m.metrics.get("steps_saved", 0)),
                          "schedule": int(m.metrics.get("schedule_steps", 0)), "wall_s": float(m.wall_time_s)}
    return out


def oracle_work(work: Path, oracle: OracleConfig) -> Path:
    """The runs' work folder for this oracle: the stage fingerprints do not see the oracle, so each
    oracle keeps its own stores."""
    return Path(work) / oracle.kind


def run(scenes: list[str], bases: list[Schedule], seeds: list[int], device: str, work: Path, eval_cfg: EvalConfig,
        jobs: int, log: Path, variants: tuple[bool, ...] = (False, True),
        oracle: OracleConfig | None = None, rule: str = "sides",
        stages: tuple[str, ...] = STOPPING) -> tuple[list[dict[str, Any]], list[str]]:
    """Every cell not yet in ``log``, ``jobs`` at a time; each finished record is appended to ``log``
    (JSON lines) at once, so a run cut short by a time limit keeps what it finished and the next
    run with the same log goes on from there. A cell that raises is reported (its traceback on
    stderr) and left out of ``log``, so the next run retries it; the others go on. Returns the
    records and the failed cells' labels."""
    oracle = oracle or OracleConfig()
    work = oracle_work(work, oracle)
    by_name = {s.name: s for s in make_scenes(0, scenes)}
    for scene in by_name.values():  # written once here: the workers would race on the same photo
        photo_path(scene, work / "photos")
    records = [json.loads(line) for line in log.read_text().splitlines() if line] if log.is_file() else []
    # Records from before the side views were watched stopped on the reference view alone, in the default stages.
    rules = {(r.get("stop_rule", "reference"), tuple(r.get("stop_stages", STOPPING))) for r in records
             if r["early_stop"]}
    if rules - {(rule, stages)}:
        raise ValueError(f"{log} holds early runs under the stop rule and stages {sorted(rules)}, not "
                         f"{(rule, stages)}: give these runs another --name")
    finished = {(r["base"], r["scene"], r["seed"], r["early_stop"]) for r in records}
    cells = [(base, seed, early, name) for base in bases for name in scenes for seed in seeds
             for early in variants if (base.label, name, seed, early) not in finished]
    log.parent.mkdir(parents=True, exist_ok=True)
    where = machine(device)

    failed: list[str] = []

    def finish(cell: tuple[Schedule, int, bool, str], outcome: Callable[[], list[dict[str, Any]]]) -> None:
        base, seed, early, name = cell
        try:
            result = outcome()
        except Exception:  # one broken cell must not cost the records of the cells still running
            failed.append(f"{variant_schedule(base, seed, early, rule, stages).label} {name}")
            print(f"FAILED {failed[-1]}:\n{traceback.format_exc()}", file=sys.stderr, flush=True)
            return
        rec = {**result[0], "base": base.label, "seed": seed, "early_stop": early, "oracle": oracle.kind,
               **({"stop_rule": rule, "stop_stages": list(stages)} if early else {}),
               "machine": where,
               "date": datetime.now(timezone.utc).strftime("%Y-%m-%d"),
               "steps": _steps(work, variant_schedule(base, seed, early, rule, stages), name)}
        records.append(rec)
        with log.open("a", encoding="utf-8") as fh:
            fh.write(json.dumps(rec, default=str) + "\n")

    args = [([by_name[name]], [variant_schedule(base, seed, early, rule, stages)], device, work, eval_cfg, oracle)
            for base, seed, early, name in cells]
    if jobs <= 1:
        for cell, a in zip(cells, args, strict=True):
            finish(cell, partial(run_error_time, *a))
        return records, failed
    threads = max(1, torch.get_num_threads() // jobs)
    with ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("spawn"), initializer=worker_init,
                             initargs=(threads,)) as pool:
        futures = {pool.submit(run_error_time, *a): cell for cell, a in zip(cells, args, strict=True)}
        for future in as_completed(futures):
            finish(futures[future], future.result)
    return records, failed


def early_runs(records: list[dict[str, Any]]) -> str:
    """How the records' early runs stopped, in words (records from before the side views: the reference rule)."""
    kinds = sorted({(r.get("stop_rule", "reference"), tuple(r.get("stop_stages", STOPPING))) for r in records
                    if r["early_stop"]})
    rule_words = {"reference": "the reference view alone", "sides": "the reference view and the held-out side views"}
    said = [f"{' and '.join(stages)} stopping on {rule_words[rule]}" for rule, stages in kinds]
    return "; ".join(said) or "no early runs"


def _glb(rec: dict[str, Any]) -> dict[str, float]:
    return next(p for p in rec["points"] if p["stage"] == POINTS[-1])


def _mean_sd(values: list[float]) -> tuple[float, float]:
    return statistics.fmean(values), (statistics.stdev(values) if len(values) > 1 else 0.0)


def summarise(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per (schedule, scene) and one per schedule over all its scenes, from the (schedule,
    scene, seed) cells that finished both ways (a run cut short leaves some half done)."""
    done = [r for r in records if "points" in r]
    both = {k for k in {(r["base"], r["scene"], r["seed"]) for r in done}
            if {r["early_stop"] for r in done if (r["base"], r["scene"], r["seed"]) == k} == {False, True}}
    ok = [r for r in done if (r["base"], r["scene"], r["seed"]) in both]
    rows = []
    for base in dict.fromkeys(r["base"] for r in ok):
        scenes = list(dict.fromkeys(r["scene"] for r in ok if r["base"] == base))
        for scene in [*scenes, "all scenes"]:
            pick = [r for r in ok if r["base"] == base and (scene == "all scenes" or r["scene"] == scene)]
            row: dict[str, Any] = {"schedule": base, "scene": scene}
            for early in (False, True):
                tag = "early" if early else "fixed"
                mine = [r for r in pick if r["early_stop"] is early]
                seeds = sorted({r["seed"] for r in mine})
                # Over scenes: the per-seed mean over scenes, so the spread is the seeds' spread.
                per_seed = {m: [statistics.fmean(_glb(r)[m] for r in mine if r["seed"] == s) for s in seeds]
                            for m in METRICS}
                for m in METRICS:
                    mean, sd = _mean_sd(per_seed[m])
                    row[f"{tag}_{m}"], row[f"{tag}_{m}_sd"] = mean, sd
                    row[f"{tag}_{m}_range"] = (min(per_seed[m]), max(per_seed[m]))
                row[f"{tag}_wall_s"] = statistics.fmean(_glb(r)["wall_s"] for r in mine)
                row[f"{tag}_steps"] = sum(s["run"] for r in mine for s in r["steps"].values()) / max(1, len(mine))
                row[f"{tag}_stage_steps"] = {st: statistics.fmean(r["steps"][st]["run"] for r in mine
                                                                  if st in r["steps"]) for st in OPTIMISING}
            deltas = [_glb(e)["novel_psnr"] - _glb(f)["novel_psnr"] for e in pick if e["early_stop"]
                      for f in pick if not f["early_stop"] and (f["scene"], f["seed"]) == (e["scene"], e["seed"])]
            row["paired_delta_psnr"], row["paired_delta_psnr_sd"] = _mean_sd(deltas)
            row["pairs"] = len(deltas)
            for m in METRICS:
                lo, hi = row[f"fixed_{m}_range"]
                row[f"{m}_within_spread"] = lo <= row[f"early_{m}"] <= hi
            rows.append(row)
    return rows


def markdown(rows: list[dict[str, Any]], seeds: list[int]) -> str:
    lines = ["| schedule | scene | GLB PSNR fixed (dB) | GLB PSNR early (dB) | Chamfer fixed | Chamfer early | "
             "F-score fixed | F-score early | paired Δ PSNR (dB) | within seed range | "
             "steps run fixed → early (nerf/dmtet/texture) | wall fixed (s) | wall early (s) | time saved |",
             "|---|---|" + "---:|" * 12]
    for r in rows:
        within = "/".join("yes" if r[f"{m}_within_spread"] else "no" for m in METRICS)
        steps = " / ".join(f"{r['fixed_stage_steps'][s]:.0f}→{r['early_stage_steps'][s]:.0f}" for s in OPTIMISING)
        saved = 1 - r["early_wall_s"] / r["fixed_wall_s"] if r["fixed_wall_s"] else 0.0
        name = f"**{r['scene']}**" if r["scene"] == "all scenes" else r["scene"]
        lines.append(
            f"| {r['schedule']} | {name} | {r['fixed_novel_psnr']:.2f} ± {r['fixed_novel_psnr_sd']:.2f} | "
            f"{r['early_novel_psnr']:.2f} ± {r['early_novel_psnr_sd']:.2f} | {r['fixed_chamfer']:.4f} | "
            f"{r['early_chamfer']:.4f} | {r['fixed_fscore']:.3f} | {r['early_fscore']:.3f} | "
            f"{r['paired_delta_psnr']:+.2f} ± {r['paired_delta_psnr_sd']:.2f} (n={r['pairs']}) | {within} | {steps} | "
            f"{r['fixed_wall_s']:.1f} | {r['early_wall_s']:.1f} | {saved:.0%} |")
    return ("\n".join(lines) + f"\n\n± is the standard deviation over the pipeline seeds {seeds}; 'within seed range' "
            "(PSNR/Chamfer/F-score): the early-stopping mean lies inside the fixed schedule's min–max over those "
            "seeds. Paired Δ: early − fixed GLB PSNR of the same scene and seed, mean ± sd over the pairs. "
            "Wall time: reference preparation + the four stages, mean over seeds (and scenes).\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--schedules", default="draft", help=f"comma-separated, of {sorted(BASES)}")
    ap.add_argument("--scenes", default=",".join(SCENE_NAMES))
    ap.add_argument("--seeds", default="0,1,2", help="pipeline seeds")
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--jobs", type=int, default=1, help="runs at once, each in its own process")
    ap.add_argument("--work", type=Path, default=Path("outputs/early_stop"))
    ap.add_argument("--results", type=Path, default=RESULTS)
    ap.add_argument("--name", default="")
    ap.add_argument("--oracle", choices=ORACLE_KINDS, default="stochastic",
                    help="the priors' oracle (benchmarks/oracle.py); each keeps its own stores under --work")
    ap.add_argument("--variants", default="fixed,early",
                    help="which runs of each cell: fixed, early or both; one alone only appends records "
                         "(summarise each record file with --from-records and compare the two)")
    ap.add_argument("--stop-rule", choices=STOP_RULES, default="sides",
                    help="the early runs' rule: sides (the reference view and the held-out side views, the "
                         "default) or reference (the reference view alone, as in the earlier results)")
    ap.add_argument("--stop-stages", default=",".join(STOPPING),
                    help=f"the stages the early runs may stop, comma-separated, of {OPTIMISING}")
    ap.add_argument("--from-records", type=Path, nargs="*", default=None,
                    help="summarise these JSON-lines record files (of earlier, possibly cut-short runs) instead")
    args = ap.parse_args(argv)
    unknown = [s for s in args.schedules.split(",") if s not in BASES]
    if unknown:
        ap.error(f"unknown schedule(s) {unknown}; choose from {sorted(BASES)}")
    if args.device == "cuda" and not torch.cuda.is_available():
        ap.error("--device cuda but no CUDA device is visible")
    variants = tuple(v == "early" for v in dict.fromkeys(args.variants.split(",")))
    if not variants or not set(args.variants.split(",")) <= {"fixed", "early"}:
        ap.error(f"--variants takes fixed, early or fixed,early; got {args.variants!r}")
    bases = [BASES[s] for s in args.schedules.split(",")]
    stages = tuple(s for s in args.stop_stages.split(",") if s)
    if not stages or not set(stages) <= set(OPTIMISING):
        ap.error(f"--stop-stages takes stages of {OPTIMISING}; got {args.stop_stages!r}")
    scenes, seeds = [s for s in args.scenes.split(",") if s], [int(s) for s in args.seeds.split(",") if s]
    eval_cfg = SIZES["gpu" if args.device == "cuda" else "cpu"].eval
    name = args.name or f"early_stop_{'h200' if args.device == 'cuda' else 'cpu'}"
    start = time.perf_counter()
    failed: list[str] = []
    if args.from_records is not None:
        records = [json.loads(line) for f in args.from_records for line in f.read_text().splitlines() if line]
        seeds = sorted({r["seed"] for r in records})
        scenes = list(dict.fromkeys(r["scene"] for r in records))
    else:
        records, failed = run(scenes, bases, seeds, args.device, args.work, eval_cfg, args.jobs,
                              args.results / f"{name}.records.jsonl", variants, OracleConfig.named(args.oracle),
                              args.stop_rule, stages)
        if failed:
            print(f"{len(failed)} cells failed (tracebacks above), left out: {failed}", file=sys.stderr)
        if len(variants) == 1 or not records:
            print(f"{len(records)} records in {args.results / f'{name}.records.jsonl'}")
            return 1 if failed else 0
    rows = summarise(records)
    payload = {"title": f"Early stopping on and off: {early_runs(records)}", "machine": records[0]["machine"],
               "date": records[0]["date"],
               "command": "python -m benchmarks.early_stop " + " ".join(argv if argv is not None else sys.argv[1:]),
               "wall_s": time.perf_counter() - start, "seeds": seeds, "scenes": scenes,
               "schedules": list(dict.fromkeys(r["base"] for r in records)), "rows": rows,
               "records_file": f"{name}.records.jsonl",
               "about": __doc__.split("\n\n")[1].replace("\n", " ")}
    write_results(args.results, name, payload, markdown(rows, seeds))
    print(json.dumps([{k: r[k] for k in ("schedule", "scene", "fixed_novel_psnr", "early_novel_psnr",
                                          "fixed_wall_s", "early_wall_s")} for r in rows], indent=1))
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
