"""The quality benchmark: synthetic scenes with ground truth, oracle priors, the paper's ablations,
error against run time and the stability sweep. ``make bench-quality`` runs the CPU size.

    python -m benchmarks.quality                         # CPU size, default rows and scenes (< 30 min, 2 cores)
    python -m benchmarks.quality --scenes all --rows findings --jobs 8   # every finding, every scene
    python -m benchmarks.quality --oracle noise-free     # the deterministic oracle (regressions, comparisons)
    python -m benchmarks.quality --size gpu --device cuda --parts error_time

Each part writes ``<part>_<size>.json`` (every record, the machine, the date, the command) and a
Markdown table beside it; error against time also a plot. The ablations also judge the paper's
findings (``benchmarks/findings.py``) into ``findings.json`` / ``findings.md``, one list over sizes.
Work files (photos, stores) go to ``--work``, one folder per size and oracle, and are reused: an
interrupted run picks up the finished stages.
"""

from __future__ import annotations

import argparse
import json
import logging
import multiprocessing
import os
import platform
import sys
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import torch

from assets_store.atomic import atomic_write_text
from benchmarks.ablations import FINDING_ROWS, ROWS, run_ablations
from benchmarks.error_time import run_error_time
from benchmarks.findings import findings_markdown, judge_all, write_findings
from benchmarks.oracle import ORACLE_KINDS, OracleConfig
from benchmarks.quality_report import (
    ablation_markdown,
    error_time_markdown,
    per_scene_markdown,
    plot_error_time,
    stability_markdown,
)
from benchmarks.scene_eval import EvalConfig
from benchmarks.scene_runs import Schedule, photo_path
from benchmarks.scenes import SCENE_NAMES, make_scenes
from benchmarks.stability import run_stability
from ops.engine.gpu_lease import LEASE_DIR_ENV

ROOT = Path(__file__).resolve().parent.parent
PARTS = ("ablations", "error_time", "stability")
DEFAULT_PARTS = ("ablations", "error_time")  # the stability sweep (13 runs to the GLB) on demand: --parts stability
log = logging.getLogger("morpheus3d.bench")

# The ablation schedule: the draft preset with a longer, finer texture stage, so stage 2 has the
# steps and pixels to show detail (draft's 60 steps at 96 px barely move the texture).
_BENCH_CPU = Schedule("bench-cpu", "draft", overrides=("texture.loop.steps=150", "texture.resolution=128"))


@dataclass(frozen=True)
class BenchSize:
    scenes: tuple[str, ...]
    rows: tuple[str, ...]  # the ablation rows run by default (every seed runs every row)
    ablation: Schedule
    timing: tuple[Schedule, ...]
    timing_scenes: tuple[str, ...]
    stability: Schedule
    stability_scene: str
    eval: EvalConfig = field(default_factory=EvalConfig)
    default_timing: tuple[str, ...] = ()  # the timing schedules run without --schedules (empty: all)


# The CPU default fits 30 minutes on 2 cores: the first three findings' rows on the two scenes with
# the finest detail, three seeds each; ``--scenes all --rows findings`` runs every finding.
_CPU_ROWS = ("base", "full_pass_2d", "high_pass_2d_sds", "ours")
_CPU_SCENES = ("tin", "gift")

SIZES: dict[str, BenchSize] = {
    "cpu": BenchSize(
        scenes=_CPU_SCENES, rows=_CPU_ROWS, ablation=_BENCH_CPU,
        # standard-size NeRF steps cost ~10 s on 2 cores (hash grid 2^19, normals): GPU sizes only. The
        # ablation's stage 1 and "ours" row are this schedule's stages, so only the bake and scoring run.
        timing=(_BENCH_CPU, Schedule("draft", "draft")), default_timing=("bench-cpu",),
        timing_scenes=_CPU_SCENES,
        stability=Schedule("stability-cpu", "draft", steps=(60, 30, 30)), stability_scene="mug",
    ),
    "large": BenchSize(
        scenes=SCENE_NAMES, rows=FINDING_ROWS,
        ablation=Schedule("bench-large", "standard", steps=(600, 300, 600)),
        timing=(Schedule("draft", "draft"), Schedule("standard/5", "standard", steps=(600, 300, 300)),
                Schedule("paper/20", "paper", steps=(500, 250, 250))),
        timing_scenes=SCENE_NAMES,
        stability=Schedule("stability-large", "draft"), stability_scene="mug",
        eval=EvalConfig(azimuths=16, resolution=256),
    ),
    "gpu": BenchSize(
        scenes=SCENE_NAMES, rows=FINDING_ROWS,
        ablation=Schedule("bench-gpu", "standard", steps=(1000, 500, 1000)),
        timing=(Schedule("draft", "draft"), Schedule("standard/5", "standard", steps=(600, 300, 300)),
                Schedule("paper/20", "paper", steps=(500, 250, 250))),
        timing_scenes=("mug", "box"),
        stability=Schedule("stability-gpu", "draft"), stability_scene="mug",
        eval=EvalConfig(azimuths=16, resolution=256),
    ),
}


def machine(device: str) -> str:
    if device == "cuda":
        return f"{torch.cuda.get_device_name(0)}, torch {torch.__version__}"
    return f"{platform.node()} ({platform.machine()}, {torch.get_num_threads()} threads, torch {torch.__version__})"


def write_results(results: Path, stem: str, payload: dict[str, Any], markdown: str) -> None:
    """Write a benchmark's ``<stem>.json`` (the payload) and ``<stem>.md`` (a header from it, then ``markdown``)."""
    results.mkdir(parents=True, exist_ok=True)
    atomic_write_text(results / f"{stem}.json", json.dumps(payload, indent=1, default=str, allow_nan=True) + "\n")
    if payload.get("from_records"):
        head = (f"Records from: {payload['machine']}; latest {payload['date']}; tables written by "
                f"`{payload['command']}` from `{stem}.records.jsonl`.\n\n")
    else:
        head = (f"Machine: {payload['machine']}; date: {payload['date']}; command: `{payload['command']}`; "
                f"wall time {payload['wall_s'] / 60:.1f} min.\n\n")
    atomic_write_text(results / f"{stem}.md", f"# {payload['title']}\n\n{head}{payload['about']}\n\n{markdown}")


def worker_init(threads: int) -> None:
    """A benchmark worker process: its share of the CPU threads, quiet logs, and its own GPU lease folder:
    the runs share the host's GPU on purpose (they are launch-bound), instead of queueing for the one
    device the pipeline's lease would hand out."""
    os.environ[LEASE_DIR_ENV] = tempfile.mkdtemp(prefix="bench-lease-")
    torch.set_num_threads(threads)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    logging.getLogger("morpheus3d.bench").setLevel(logging.INFO)
    for noisy in ("morpheus3d", "morpheus3d.pipeline"):
        logging.getLogger(noisy).setLevel(logging.ERROR)


Call = tuple[Callable[..., list[dict[str, Any]]], tuple[Any, ...]]


def run_calls(calls: list[Call], jobs: int) -> list[list[dict[str, Any]]]:
    """Each ``fn(*args)`` of ``calls``, in ``jobs`` processes at once when > 1 (scenes are independent:
    each has its own keys in the store, so results do not depend on it); results in call order."""
    if jobs <= 1 or len(calls) <= 1:
        return [fn(*a) for fn, a in calls]
    threads = max(1, torch.get_num_threads() // jobs)
    with ProcessPoolExecutor(min(jobs, len(calls)), mp_context=multiprocessing.get_context("spawn"),
                             initializer=worker_init, initargs=(threads,)) as pool:
        futures = [pool.submit(fn, *a) for fn, a in calls]
        return [f.result() for f in futures]


def logged_ablations(log_path: Path, stamp: dict[str, Any], *args: Any) -> list[dict[str, Any]]:
    """``run_ablations(*args)`` appending each finished record (with ``stamp``) to ``log_path`` at once, in
    one write of one line (appends of whole lines from parallel workers do not interleave); failed rows are
    logged, not saved, so the next run retries them."""
    def save(record: dict[str, Any]) -> None:
        if "error" in record:
            log.warning("%s/%s failed (retried next run): %s", record["scene"], record["row"], record["error"])
            return
        with log_path.open("a", encoding="utf-8") as fh:
            fh.write(json.dumps({**record, **stamp}, default=str) + "\n")

    return run_ablations(*args, on_record=save)


def _read_jsonl(path: Path) -> list[dict[str, Any]]:
    """The records of a JSON-lines log; a line cut short by a kill is skipped (its call runs again)."""
    records = []
    for line in path.read_text().splitlines() if path.is_file() else []:
        try:
            records.append(json.loads(line))
        except ValueError:
            log.warning("%s: skipping a line cut short (%d characters)", path, len(line))
    return records


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--size", choices=sorted(SIZES), default="cpu")
    ap.add_argument("--parts", default=",".join(DEFAULT_PARTS),
                    help=f"comma-separated subset of {', '.join(PARTS)} (default: {', '.join(DEFAULT_PARTS)})")
    ap.add_argument("--scenes", default="", help="comma-separated scene names for the ablations and error against "
                                                 "time, or 'all' (default: the size's)")
    ap.add_argument("--oracle", choices=ORACLE_KINDS, default="stochastic",
                    help="the priors' oracle: stochastic (errs like a real denoiser, the default) or noise-free")
    ap.add_argument("--schedules", default="", help="comma-separated labels of the size's timing schedules to run "
                                                    "(default: the size's default ones, else all)")
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--work", type=Path, default=ROOT / "outputs" / "bench_quality")
    ap.add_argument("--results", type=Path, default=ROOT / "benchmarks" / "results")
    ap.add_argument("--seed", type=int, default=0, help="the scenes' seed")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a config override for every schedule of the run (one configuration for all scenes)")
    ap.add_argument("--tag", default="", help="suffix of the result files (e.g. for a --set variant)")
    ap.add_argument("--rows", default="", help="comma-separated ablation rows, 'findings' (the rows the findings "
                                               "need) or 'all' (default: the size's)")
    ap.add_argument("--jobs", type=int, default=1, help="scenes run in this many processes at once (the CPU threads "
                                                        "are shared out between them); results are the same")
    ap.add_argument("--ablation-seeds", default="0,1,2",
                    help="pipeline seeds: every seed runs every row, for the spread the findings are judged against")
    ap.add_argument("--from-records", action="store_true",
                    help="run nothing: write the ablation tables and findings from the records log alone (e.g. records "
                         "brought back from a GPU machine)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    for noisy in ("morpheus3d", "morpheus3d.pipeline"):
        logging.getLogger(noisy).setLevel(logging.ERROR)
    logging.getLogger("morpheus3d.bench").setLevel(logging.INFO)
    parts = [p for p in args.parts.split(",") if p]
    unknown = sorted(set(parts) - set(PARTS))
    if unknown:
        ap.error(f"unknown part(s) {unknown}; choose from {PARTS}")
    if args.device == "cuda" and not torch.cuda.is_available() and not args.from_records:
        ap.error("--device cuda but no CUDA device is visible")
    size = SIZES[args.size]
    if args.set:
        def extend(s: Schedule) -> Schedule:
            return replace(s, overrides=(*s.overrides, *args.set))
        size = replace(size, ablation=extend(size.ablation), timing=tuple(extend(s) for s in size.timing),
                       stability=extend(size.stability))
    chosen = SCENE_NAMES if args.scenes == "all" else tuple(s for s in args.scenes.split(",") if s)
    names, timing_names = chosen or size.scenes, chosen or size.timing_scenes
    scenes = {s.name: s for s in make_scenes(args.seed, tuple(dict.fromkeys(
        (*names, *timing_names, size.stability_scene))))}
    tag = args.size if args.device == "cpu" or args.size == "gpu" else f"{args.size}_{args.device}"
    tag += f"_{args.tag}" if args.tag else ""
    oracle = OracleConfig.named(args.oracle)
    tag += "_noise-free" if oracle.kind == "noise-free" else ""
    common = {"machine": "(the records' machines)" if args.from_records else machine(args.device),
              "date": datetime.now(timezone.utc).strftime("%Y-%m-%d"),
              "command": "python -m benchmarks.quality " + " ".join(argv if argv is not None else sys.argv[1:]),
              "size": args.size, "device": args.device, "seed": args.seed, "eval": asdict(size.eval),
              "oracle": oracle.describe(), "oracle_kind": oracle.kind,
              "overrides": list(args.set), "from_records": args.from_records}
    work = args.work / tag
    if "ablations" in parts:
        t0 = time.perf_counter()
        seeds = [int(s) for s in args.ablation_seeds.split(",") if s]
        wanted_rows = {"": size.rows, "findings": FINDING_ROWS, "all": tuple(r.name for r in ROWS)}.get(
            args.rows, tuple(n for n in args.rows.split(",") if n))
        unknown = sorted(set(wanted_rows) - {r.name for r in ROWS})
        if unknown:
            ap.error(f"unknown row(s) {unknown}; choose from {[r.name for r in ROWS]}, 'findings' or 'all'")
        rows = tuple(r for r in ROWS if r.name in wanted_rows)
        # Each (seed, scene) call's records are appended to a JSON-lines log as it finishes: a run cut
        # short keeps them, and the next run with the same results folder goes on from there.
        log_path = args.results / f"quality_ablations_{tag}.records.jsonl"
        row_names = {r.name for r in rows}
        kept = [r for r in _read_jsonl(log_path) if r["seed"] in seeds and r["scene"] in names]
        have: dict[tuple[int, str], set[str]] = {}
        for r in kept:
            have.setdefault((r["seed"], r["scene"]), set()).add(r["row"])
        for scene in scenes.values():  # written once here: parallel calls of one scene would race on its photo
            photo_path(scene, work / "photos")
        calls: list[Call] = []
        for seed in seeds:
            schedule = size.ablation if seed == 0 else replace(
                size.ablation, label=f"{size.ablation.label}-seed{seed}",
                overrides=(*size.ablation.overrides, f"seed={seed}"))
            for n in names:
                missing = tuple(r for r in rows if r.name not in have.get((seed, n), set()))
                if missing:
                    stamp = {"seed": seed, "machine": common["machine"], "date": common["date"]}
                    calls.append((logged_ablations, (log_path, stamp, [scenes[n]], schedule, args.device, work,
                                                     size.eval, missing, oracle)))
        args.results.mkdir(parents=True, exist_ok=True)
        if not args.from_records:
            run_calls(calls, args.jobs)
        kept = [r for r in _read_jsonl(log_path) if r["seed"] in seeds and r["scene"] in names]
        ran_on = sorted({r["machine"] for r in kept if r.get("machine")})
        if ran_on:  # the records say where they ran (several machines when a run went on elsewhere)
            common = {**common, "machine": "; ".join(ran_on), "date": max(r["date"] for r in kept if r.get("date"))}
        latest = {(r["seed"], r["scene"], r["row"]): r for r in kept}  # a resumed call re-scores stage 1
        by_seed = {seed: [r for (s_, _, row), r in latest.items() if s_ == seed and row in row_names | {"stage1"}]
                   for seed in seeds}
        records = by_seed[seeds[0]]
        judged = judge_all(by_seed, f"{size.ablation.label}, {oracle.kind} oracle, {args.device}")
        write_findings(args.results, judged)
        write_results(args.results, f"quality_ablations_{tag}", {
            **common, "title": "Ablations on synthetic scenes with oracle priors", "wall_s": time.perf_counter() - t0,
            "schedule": asdict(size.ablation), "scenes": list(names), "records": records,
            "seed_records": {str(k): v for k, v in by_seed.items()}, "findings": judged,
            "about": _ABOUT_ABLATIONS.format(schedule=size.ablation, scenes=", ".join(names),
                                             oracle=common["oracle"], eval=size.eval)},
            ablation_markdown(records) + f"\n### The paper's findings (seeds {', '.join(map(str, seeds))})\n\n"
            + findings_markdown(judged) + "\n### Per scene\n\n" + per_scene_markdown(records))
    if "error_time" in parts:
        t0 = time.perf_counter()
        timing_scenes = [scenes[n] for n in timing_names]
        wanted = [s for s in args.schedules.split(",") if s] or list(size.default_timing)
        timing = [s for s in size.timing if not wanted or s.label in wanted]
        if not timing:
            ap.error(f"--schedules {args.schedules!r} matches none of {[s.label for s in size.timing]}")
        calls = [(run_error_time, ([scene], [schedule], args.device, work, size.eval, oracle))
                 for schedule in timing for scene in timing_scenes]
        records = [r for part in run_calls(calls, args.jobs) for r in part]
        plot = plot_error_time(records, args.results / f"error_vs_time_{tag}.png",
                               f"Error against run time ({common['machine']})")
        write_results(args.results, f"error_vs_time_{tag}", {
            **common, "title": "Error against run time", "wall_s": time.perf_counter() - t0,
            "schedules": [asdict(s) for s in timing], "scenes": list(timing_names), "records": records,
            "about": _ABOUT_TIME.format(scenes=", ".join(timing_names), plot=plot.name)},
            error_time_markdown(records))
    if "stability" in parts:
        t0 = time.perf_counter()
        records = run_stability(scenes[size.stability_scene], size.stability, args.device, work, size.eval,
                                oracle=oracle)
        bad = [r["entry"] for r in records if not (r["finished"] and r.get("finite_outputs"))]
        write_results(args.results, f"stability_{tag}", {
            **common, "title": "Stability on stiff and extreme settings", "wall_s": time.perf_counter() - t0,
            "schedule": asdict(size.stability), "records": records,
            "about": _ABOUT_STABILITY.format(scene=size.stability_scene, schedule=size.stability,
                                             bad=", ".join(bad) or "none")},
            stability_markdown(records))
    return 0


_ABOUT_ABLATIONS = """\
Scenes: {scenes} (`benchmarks/scenes/`, seed 0). Each scene's product photo goes through the real
pipeline (reference → NeRF → DMTet → texture) with the oracle priors ({oracle}). Stage 1 runs once
per scene; every row re-runs only stage 2 from the same DMTet output, with one configuration for all
scenes: schedule `{schedule.label}` (preset `{schedule.preset}`, overrides {schedule.overrides}).
Metrics against the ground truth over {eval.azimuths} azimuths × elevations {eval.elevations} at
{eval.resolution} px, the reference view left out: novel-view PSNR/SSIM on white, HF ratio = the
views' high-frequency energy share (≥ {eval.hf_cutoff} Nyquist, inside the object) over the truth's
(1 = as detailed), colour deviation = 1 − Bhattacharyya coefficient of a*b* histograms inside the
objects (0 = same colours), Chamfer distance and F-score (τ = {eval.fscore_threshold}) between the
visible surfaces (points from depth maps; objects span ≈ 1.46 units). Tables show means over scenes.

With the noise-free oracle two rows are identical by construction (the ideal VSD counterpart of a
render-target prior is the current render, so VSD's residual equals SDS's); the stochastic oracle's
VSD counterpart repeats part of the frozen prior's error, so they differ (README, "The stochastic
oracle"). Every seed runs every row; the findings table judges each claim against the seed spread.
"""


_ABOUT_TIME = """\
Scenes: {scenes}. Each schedule runs the whole pipeline with the oracle priors; after every stage
its output is scored against the ground truth (NeRF by volume rendering, DMTet and texture stages
as mesh + texture field, then the exported GLB). Wall time is cumulative from the stage manifests
(reference preparation included). Mean over the scenes. Plot: `{plot}` (right panel: the stages'
own reference-view PSNR logs for the first scene).
"""

_ABOUT_STABILITY = """\
Scene `{scene}`, schedule `{schedule.label}` (preset `{schedule.preset}`, steps {schedule.steps}).
Each row changes one thing in all three optimising stages (or the photo's framing) and runs the
pipeline to the GLB. Guard events: steps skipped for a NaN/Inf prior output, loss or gradient,
rollbacks of non-finite parameters, and restores of the last good state, summed over the stages.
Finite outputs: the GLB's vertices, UVs and texture (every stage also refuses to write a non-finite
tensor). Novel-view metrics are left out for the cut-off photo (its frame is not the truth's).
Runs that did not finish with finite outputs: {bad}.
"""


if __name__ == "__main__":
    raise SystemExit(main())
