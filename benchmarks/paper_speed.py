"""The paper's schedule on one GPU: minutes per object and objects per GPU-hour, before and after.

Every optimising stage runs through the task classes the pipeline uses, with the real prior code
on full-size architectures and random weights (compute does not depend on the weight values):
Zero123 SDS for the NeRF and DMTet stages; Zero123 SDS + SD1.5/ControlNet/IP-Adapter VSD with one
LoRA per object for the texture stage; the paper preset's step counts and resolutions. Each
(stage, batch) row times steady-state steps after warm-up (CUDA graphs and compiled kernels are
built during warm-up) and extrapolates to the preset's schedule (the paper's 10k + 5k + 5k steps);
a stage with coarse render phases (the ``fast`` preset) gets one row per phase, each extrapolated to
that phase's steps; per-object set-up (NeRF → DMTet initialisation, writing outputs) is timed
separately and added.

Modes: ``before`` = the unoptimised path (eager priors, eager hash grid, one object at a time);
``after`` = the defaults now (priors from CUDA graphs, compiled hash grid) with several objects per
batch (``ops.engine.batch``).

    python benchmarks/paper_speed.py --device cuda --mode before --batches 1 --profile --tag h200
    python benchmarks/paper_speed.py --device cuda --mode after --batches 1 4 8 16 --profile 1 8 --tag h200
    python benchmarks/paper_speed.py --device cuda --mode after --preset fast --batches 1 --tag fast_h100
    python benchmarks/paper_speed.py --device cpu --scale tiny --preset draft --batches 1 2 --steps 2  # smoke
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import sys
import tempfile
import time
import traceback
from dataclasses import replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import torch

from assets_store.atomic import atomic_write_text
from assets_store.store import Store
from benchmarks.prior_speed import build_priors
from benchmarks.timing import sync_device
from morpheus_core.priors.runtime import PriorRuntime
from morpheus_core.runtime.cuda_graphs import GraphedCall
from morpheus_core.runtime.execution import apply_execution, current_execution
from ops.config.presets import PipelineConfig, preset
from ops.engine.batch import BatchTask
from ops.engine.loop import GuardCounters, LoopConfig, LoopResult, run_loop
from ops.engine.priors import RealSuite
from ops.engine.render_phases import RenderSchedule
from ops.engine.stage_job import StageJob
from ops.engine.target import read_rgba
from ops.pipeline.runner import Pipeline
from ops.stages.dmtet import start_dmtet
from ops.stages.nerf import start_nerf
from ops.stages.texture import start_texture

ROOT = Path(__file__).resolve().parent.parent
PHOTOS = ROOT / "examples" / "photos"
STAGES = ("nerf", "dmtet", "texture")
# The paper on an RTX 4090 (DESIGN.md §7): NeRF 26 + DMTet 14 + texture 72 minutes.
PAPER_MIN = {"nerf": 26.0, "dmtet": 14.0, "texture": 72.0}
MODES = {"before": {"accel": "eager", "compile": "0"}, "after": {"accel": "cudagraph", "compile": "1"}}


def prepare_references(store_root: Path, cfg: PipelineConfig) -> list[Path]:
    """The example photos' reference folders (prepared once, reused: segmentation is CPU work)."""
    store = Store(store_root)
    dirs = []
    for photo in sorted(PHOTOS.glob("*.jpg")):
        out = Pipeline(store, cfg, "paper").run([(photo, photo.name)], ["reference"])[0]
        if out.error:
            raise RuntimeError(out.error)
        dirs.append(store.stage_dir(photo.name, "reference"))
    return dirs


class Rig:
    """The full-size priors of one mode and the inputs every stage's jobs start from."""

    def __init__(self, cfg: PipelineConfig, dev: torch.device, refs: list[Path], scale: str, work: Path) -> None:
        self.cfg, self.dev, self.refs, self.work = cfg, dev, refs, work
        dtype = torch.float16 if dev.type == "cuda" else torch.float32
        runtime = PriorRuntime(str(dev), dtype, channels_last=dev.type == "cuda", accel=cfg.priors.accel)
        built = build_priors(scale, runtime, 0, with_2d=True)
        self.models = {"3d": built.zero123, "2d": built.image2d}
        self.nerf_dir: Path | None = None
        self.dmtet_dir: Path | None = None

    def suite(self, key: str, ref: Path, roles: tuple[str, ...], vsd_roles: tuple[str, ...]) -> RealSuite:
        return RealSuite(self.cfg.priors, self.dev, key, read_rgba(ref, 256), roles, vsd_roles, self.models)

    def job(self, stage: str, i: int, phase: int = -1) -> StageJob:
        """Object ``i``'s job of ``stage``, every step rendered as render phase ``phase`` (-1: the final one)."""
        cfg, ref = phase_config(self.cfg, stage, phase), self.refs[i % len(self.refs)]
        key, out = f"obj{i}", self.work / f"{stage}_{i}"
        out.mkdir(parents=True, exist_ok=True)
        g = getattr(cfg, stage).guidance
        suite = self.suite(key, ref, g.roles, g.vsd_roles)
        try:
            if stage == "nerf":
                return start_nerf(ref, out, cfg.nerf, cfg.priors, key, str(self.dev), i, suite)
            if stage == "dmtet":
                return start_dmtet(ref, out, cfg.dmtet, cfg.priors, key, self.nerf_dir, None, None, str(self.dev),
                                   i, suite)
            return start_texture(ref, self.dmtet_dir, out, cfg.texture, cfg.priors, key, str(self.dev), i, suite)
        except BaseException:  # a LoRA left on the shared UNet would block the next row's object
            suite.close()
            raise


def phase_config(cfg: PipelineConfig, stage: str, phase: int) -> PipelineConfig:
    """``cfg`` with ``stage`` rendering every step as its render phase ``phase`` does (-1: the final one)."""
    stage_cfg = getattr(cfg, stage)
    if not stage_cfg.phases or phase == -1:
        return replace(cfg, **{stage: replace(stage_cfg, phases=())})
    p = stage_cfg.phases[phase]
    return replace(cfg, **{stage: replace(stage_cfg, phases=(), resolution=p.resolution, n_views=p.n_views)})


def phase_steps(cfg: PipelineConfig, stage: str) -> list[tuple[int, int]]:
    """(phase, steps in it) of ``stage``'s schedule, the final phase as -1."""
    sched = RenderSchedule.of(getattr(cfg, stage))
    counts: dict[int, int] = {}
    for step in range(sched.steps):
        shape = sched.at(step)
        index = -1 if shape.final else shape.index
        counts[index] = counts.get(index, 0) + 1
    return sorted(counts.items(), key=lambda kv: (kv[0] == -1, kv[0]))


def build_rig(device: str, mode: str, preset_name: str, scale: str, overrides: list[str], store: Path,
              work: Path, tf32: bool = True) -> Rig:
    """The mode's settings (``MODES``) applied to this process, the example references prepared in
    ``store`` and the priors built: what every timed row starts from."""
    dev = torch.device(device)
    accel = MODES[mode]["accel"] if dev.type == "cuda" else "eager"
    compiled = "true" if MODES[mode]["compile"] == "1" else "false"
    cfg = preset(preset_name, [f"device={device}", "priors.kind=real", f"priors.accel={accel}",
                               f"execution.compile={compiled}", *overrides])
    apply_execution(cfg.execution)  # as a run does at start-up: the rows start the stages directly
    if dev.type == "cuda":  # TF32 as in every earlier speed result; the pipeline itself keeps fp32 matmuls
        torch.backends.cuda.matmul.allow_tf32 = tf32
        torch.backends.cudnn.allow_tf32 = True
    refs = prepare_references(store, preset(preset_name, ["device=cpu"]))
    return Rig(cfg, dev, refs, scale, work)


def _timed_loop(task: Any, steps: int, warmup: int, dev: torch.device, gen: torch.Generator) -> dict[str, float]:
    t0 = time.perf_counter()
    run_loop(task, LoopConfig(warmup, log_every=10**9), gen, "warmup")
    sync_device(dev)
    warm_s = time.perf_counter() - t0
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats(dev)
    captures = GraphedCall.captures
    start = time.perf_counter()
    res = run_loop(task, LoopConfig(steps, log_every=10**9), gen, "timed")
    sync_device(dev)
    ms = (time.perf_counter() - start) * 1000 / steps  # the mean: it includes the occupancy refreshes
    if res.guards.skipped:
        raise FloatingPointError(f"{res.guards.skipped} timed steps were skipped: {res.guards.as_dict()}")
    # Reserved, not allocated: a CUDA graph's activations are free blocks of its private pool between
    # replays, which max_memory_allocated does not count.
    peak = round(torch.cuda.max_memory_reserved(dev) / 2**30, 2) if dev.type == "cuda" else None
    # Non-zero: a graph cache is too small for the shapes a step uses, and every step captures again.
    return {"ms_per_step": round(ms, 2), "peak_gib": peak, "warmup_s": round(warm_s, 1),
            "graph_captures_timed": GraphedCall.captures - captures}


def _profile(task: Any, dev: torch.device, gen: torch.Generator, rows: int = 25) -> str:
    from torch.profiler import ProfilerActivity, profile

    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if dev.type == "cuda" else [])
    with profile(activities=acts) as prof:
        start = time.perf_counter()
        run_loop(task, LoopConfig(3, log_every=10**9), gen, "profile")
        sync_device(dev)
        wall_ms = (time.perf_counter() - start) * 1000
    key = "self_cuda_time_total" if dev.type == "cuda" else "self_cpu_time_total"
    # Wall time next to the CUDA total says whether the steps were bound by the GPU or by the host.
    return (f"wall time of the 3 profiled steps: {wall_ms:.1f} ms (profiler overhead included)\n"
            + prof.key_averages().table(sort_by=key, row_limit=rows, max_name_column_width=70))


def host_syncs(task: Any, dev: torch.device, gen: torch.Generator, steps: int = 3) -> tuple[float, str]:
    """Host syncs per steady-state step under CUDA's sync debug mode, and the repository lines that
    cause them: a run of 1 + ``steps`` steps minus a run of 1, so the loop's start (state copy for
    restores) and its one guard read at the end are left out."""
    import traceback as tb
    import warnings

    if dev.type != "cuda":
        return 0.0, ""
    root = str(ROOT)

    def count(n: int) -> dict[str, int]:
        sites: dict[str, int] = {}

        def record(*_args: Any, **_kwargs: Any) -> None:
            frames = [f for f in tb.extract_stack()[:-1]
                      if f.filename.startswith(root) and not any(d in f.filename for d in ("/benchmarks/", "/.venv/"))]
            where = f"{Path(frames[-1].filename).relative_to(ROOT)}:{frames[-1].lineno}" if frames else "(outside)"
            sites[where] = sites.get(where, 0) + 1

        with warnings.catch_warnings():
            warnings.simplefilter("always")
            warnings.showwarning = record  # type: ignore[assignment]
            torch.cuda.set_sync_debug_mode("warn")
            try:
                run_loop(task, LoopConfig(n, log_every=10**9), gen, "syncs")
            finally:
                torch.cuda.set_sync_debug_mode("default")
        return sites

    one, more = count(1), count(1 + steps)
    per_step = {k: (more.get(k, 0) - one.get(k, 0)) / steps for k in set(one) | set(more)}
    per_step = {k: v for k, v in per_step.items() if v > 0}
    table = "\n".join(f"    {v:6.1f}  {k}" for k, v in sorted(per_step.items(), key=lambda kv: -kv[1]))
    return round(sum(per_step.values()), 1), f"host syncs per step (steady state, {steps} steps):\n{table}\n"


def measure_stage(rig: Rig, stage: str, batch: int, steps: int, warmup: int, profile: bool,
                  phase: int = -1) -> tuple[dict, str]:
    """One (stage, batch, render phase) row; writes object 0's output when it is the first batch of the
    final phase (the next stage's input)."""
    dev = rig.dev
    t0 = time.perf_counter()
    jobs = []
    try:
        for i in range(batch):
            jobs.append(rig.job(stage, i, phase))
        setup_s = (time.perf_counter() - t0) / batch
        task = jobs[0].task if batch == 1 else BatchTask([j.task for j in jobs], [j.generator for j in jobs])
        gen = torch.Generator().manual_seed(0)
        shape = RenderSchedule.of(getattr(phase_config(rig.cfg, stage, phase), stage)).at(0)
        row = {"stage": stage, "batch": batch, "phase": phase, "resolution": shape.resolution,
               "n_views": shape.n_views, "setup_s_per_object": round(setup_s, 2)}
        row |= _timed_loop(task, steps, warmup, dev, gen)
        table = ""
        if profile:
            row["host_syncs_per_step"], syncs = host_syncs(task, dev, gen)
            table = _profile(task, dev, gen) + "\n" + syncs
        if stage != "texture" and phase == -1 and (rig.nerf_dir if stage == "nerf" else rig.dmtet_dir) is None:
            jobs[0].finish(LoopResult([], GuardCounters(), None, 0, 0.0))
            out = rig.work / f"{stage}_0"
            if stage == "nerf":
                rig.nerf_dir = out
            else:
                rig.dmtet_dir = out
        if stage == "dmtet":
            row["faces"] = jobs[0].task.mesh().num_faces
        return row, table
    finally:
        for j in jobs:
            j.close()
        if dev.type == "cuda":
            torch.cuda.empty_cache()


def projections(rows: list[dict], schedule: dict[str, list[tuple[int, int]]]) -> list[dict]:
    """Minutes per object and objects per GPU-hour per batch size (every stage and render phase measured
    at it); ``schedule``: each stage's (render phase, steps in it)."""
    out = []
    for batch in sorted({r["batch"] for r in rows}):
        per = {(r["stage"], r.get("phase", -1)): r for r in rows if r["batch"] == batch and "ms_per_step" in r}
        if any((s, p) not in per for s in STAGES for p, _ in schedule[s]):
            continue
        stage_min = {s: sum(per[(s, p)]["ms_per_step"] * n for p, n in schedule[s]) / batch / 60000
                     + per[(s, -1)]["setup_s_per_object"] / 60 for s in STAGES}
        total = sum(stage_min.values())
        out.append({"batch": batch, **{f"{s}_min": round(v, 2) for s, v in stage_min.items()},
                    "min_per_object": round(total, 2), "objects_per_gpu_hour": round(60 / total, 2),
                    "peak_gib": max((r["peak_gib"] or 0.0) for r in per.values()) or None})
    return out


def to_markdown(res: dict) -> str:
    sched = {s: sum(n for _, n in v) if isinstance(v, list) else v for s, v in res["schedule"].items()}
    lines = [f"# Paper schedule speed, mode `{res['mode']}` — {res['device']}, {res['date']}", "",
             f"torch {res['torch']}; full-size prior architectures with random weights ({res['scale']}); "
             f"priors accel `{res['accel']}`, compiled hash grid: {res['compiled']}, hash-grid kernels "
             f"`{res.get('hashgrid', 'auto')}` (execution.hashgrid), field heads `{res.get('field_mlp', 'eager')}` "
             f"(execution.field_mlp), fp32 matmuls {'in TF32' if res.get('tf32', True) else 'at full precision'}; "
             f"{res['warmup']} warm-up + {res['steps']} timed steps per row (mean); schedule "
             f"{sched['nerf']} + {sched['dmtet']} + {sched['texture']} steps. "
             f"Command: `{res['command']}`.", "",
             "Minutes per object = Σ stages (ms/step × steps / batch + set-up per object), extrapolated from the "
             "steady-state steps (one run cannot hold the whole schedule in a 10-minute device call). Peak memory: "
             + ("the allocator's reserved peak during the timed steps (CUDA graphs keep their pools)."
                if res.get("peak") == "reserved" else "max_memory_allocated during the timed steps (older runs: "
                "this misses the activations CUDA graphs keep in their pools)."), "",
             "| stage | batch | render phase | ms/step | ms per object-step | peak GiB | set-up s/object | warm-up s |",
             "|---|---:|---|---:|---:|---:|---:|---:|"]
    for r in res["rows"]:
        if "error" in r:
            lines.append(f"| {r['stage']} | {r['batch']} | {r.get('phase', -1)} | error: {r['error'][:120]} | | | | |")
            continue
        phase = (f"{'final' if r.get('phase', -1) == -1 else r['phase']}: {r['resolution']} px × {r['n_views']} views"
                 if "resolution" in r else "final")
        lines.append(f"| {r['stage']} | {r['batch']} | {phase} | {r['ms_per_step']} | "
                     f"{r['ms_per_step'] / r['batch']:.1f} | "
                     f"{r['peak_gib']} | {r['setup_s_per_object']} | {r['warmup_s']} |")
    lines += ["", "| batch | NeRF min | DMTet min | texture min | **min / object** | **objects / GPU-hour** | "
              "peak GiB |", "|---:|---:|---:|---:|---:|---:|---:|"]
    for p in res["projections"]:
        lines.append(f"| {p['batch']} | {p['nerf_min']} | {p['dmtet_min']} | {p['texture_min']} | "
                     f"**{p['min_per_object']}** | **{p['objects_per_gpu_hour']}** | {p['peak_gib']} |")
    recaptured = [f"{r['stage']} at batch {r['batch']} ({r['graph_captures_timed']})" for r in res["rows"]
                  if r.get("graph_captures_timed")]
    if recaptured:
        lines += ["", "**CUDA graphs were captured during the timed steps** (their cache is too small for the "
                  "shapes a step uses): " + ", ".join(recaptured) + "."]
    syncs = [f"{r['stage']} {r['host_syncs_per_step']}" for r in res["rows"] if "host_syncs_per_step" in r]
    if syncs:
        lines += ["", "Host syncs per steady-state step of the profiled rows (CUDA sync debug mode; sites in the "
                  "profile file): "
                  + ", ".join(syncs) + "."]
    lines += ["", f"Paper (RTX 4090): {sum(PAPER_MIN.values()):.0f} min per object "
              f"({' + '.join(f'{v:.0f}' for v in PAPER_MIN.values())})."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda")
    p.add_argument("--mode", choices=sorted(MODES), default="after")
    p.add_argument("--preset", default="paper")
    p.add_argument("--scale", default="full", choices=["full", "tiny"])
    p.add_argument("--batches", type=int, nargs="+", default=[1, 4, 8, 16])
    p.add_argument("--stages", nargs="+", default=list(STAGES), choices=STAGES)
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--warmup", type=int, default=6)
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="a setting of the preset, as for `morpheus3d run` (A/B runs of one lever)")
    p.add_argument("--profile", type=int, nargs="*", default=None, metavar="BATCH",
                   help="profile 3 steps of the rows at these batch sizes (none given: batch 1)")
    p.add_argument("--store", type=Path, default=ROOT / "outputs" / "gpu_refs", help="where references are prepared")
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    p.add_argument("--tag", default="cpu")
    p.add_argument("--fp32-matmul", action="store_true",
                   help="keep fp32 matmuls at full precision, as the pipeline does (default: TF32, as earlier results)")
    args = p.parse_args(argv)

    work = Path(tempfile.mkdtemp(prefix="paper_speed_"))
    t_start = time.perf_counter()
    rig = build_rig(args.device, args.mode, args.preset, args.scale, args.overrides, args.store, work,
                    tf32=not args.fp32_matmul)
    cfg, dev, accel = rig.cfg, rig.dev, rig.cfg.priors.accel
    rows: list[dict] = []
    profiles: list[str] = []
    schedule = {s: phase_steps(cfg, s) for s in STAGES}
    name = torch.cuda.get_device_name(dev) if dev.type == "cuda" else platform.processor() or platform.machine()
    stem = args.out / f"paper_speed_{args.mode}_{args.tag}"
    args.out.mkdir(parents=True, exist_ok=True)

    def write() -> str:  # after every row: a call cut short by its time limit keeps what it measured
        res = {"date": datetime.now(timezone.utc).strftime("%Y-%m-%d"), "device": name, "torch": torch.__version__,
               "mode": args.mode, "accel": accel, "peak": "reserved",
               "compiled": dev.type == "cuda" and current_execution().compile,
               "hashgrid": current_execution().hashgrid,
               "field_mlp": current_execution().field_mlp, "tf32": not args.fp32_matmul,
               "scale": args.scale, "preset": args.preset, "steps": args.steps, "warmup": args.warmup,
               "schedule": schedule, "rows": rows, "projections": projections(rows, schedule),
               "wall_s": round(time.perf_counter() - t_start, 1),
               "command": "python benchmarks/paper_speed.py " + " ".join(argv if argv is not None else sys.argv[1:])}
        atomic_write_text(stem.with_suffix(".json"), json.dumps(res, indent=2) + "\n")
        atomic_write_text(stem.with_suffix(".md"), to_markdown(res))
        if profiles:
            atomic_write_text(args.out / f"paper_profile_{args.mode}_{args.tag}.txt", "\n\n".join(profiles) + "\n")
        return to_markdown(res)

    for needed in STAGES[:STAGES.index(args.stages[0])]:  # the first timed stage's inputs: short runs, not reported
        measure_stage(rig, needed, 1, 2, 2, False)
    for stage in args.stages:
        for batch, (phase, _) in [(b, p) for b in sorted(args.batches) for p in reversed(schedule[stage])]:
            try:  # the final phase first: it writes the next stage's input
                profiled = args.profile is not None and batch in (args.profile or [1]) and phase == -1
                row, table = measure_stage(rig, stage, batch, args.steps, args.warmup, profiled, phase)
                if table:
                    profiles.append(f"## {stage}, batch {batch}, mode {args.mode}\n{table}")
            except Exception as exc:  # e.g. out of memory at a large batch: record it, go on
                traceback.print_exc()
                row = {"stage": stage, "batch": batch, "phase": phase, "error": repr(exc)[:300]}
                if dev.type == "cuda":
                    torch.cuda.empty_cache()
            rows.append(row)
            print(json.dumps(row), flush=True)
            write()
    print(write())
    shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
