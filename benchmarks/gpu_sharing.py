"""Several runs on one GPU: does a second process fill the gaps a host-bound step leaves?

The profiles (``paper_profile_after_h200_*.txt``) show every stage waiting for the host at 8
objects per batch: the GPU works 57 (NeRF), 28 (DMTet) and 69 ms (texture) of a 98, 76 and 109 ms
object-step. A second process on the same GPU can launch its kernels while the first one is busy
in Python, so catalog throughput may rise although each run gets slower.

Worker processes (``--workers`` of them) each build the full-size priors once, then for every
share ``PxB`` (P processes with B objects each) and every stage: the first P workers set up a
batch of B objects, warm it up, wait for each other, step for ``--seconds`` and wait again, so
the timed windows of one (share, stage) coincide and nothing else runs on the GPU meanwhile. The
aggregate is the object-steps all P processes made per second; minutes per object and objects per
GPU-hour are extrapolated to the paper's schedule from it, as ``paper_speed.py`` does.

A backfill's runs are rarely in the same stage at once. ``--mix nerf:4 texture:4`` times each
such process alone, then all together: the share of its alone rate each one keeps, summed, is the
throughput against running them one after another.

    python -m benchmarks.gpu_sharing --device cuda --shares 1x8 2x4 2x8 --seconds 20 --tag h200
    python -m benchmarks.gpu_sharing --device cuda --shares --mix nerf:4 texture:4 --tag h200_mix  # stages mixed
    python -m benchmarks.gpu_sharing --device cpu --scale tiny --preset draft --shares 1x1 2x1 --seconds 2  # smoke
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
import traceback
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import torch

from assets_store.atomic import atomic_write_text
from benchmarks.paper_speed import STAGES, Rig, build_rig, measure_stage, prepare_references
from benchmarks.timing import sync_device
from ops.config.presets import preset
from ops.engine.batch import BatchTask
from ops.engine.loop import LoopConfig, run_loop

ROOT = Path(__file__).resolve().parent.parent


def parse_share(text: str) -> tuple[int, int]:
    """``"2x4"`` → (2 processes, 4 objects each)."""
    try:
        procs, batch = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"a share is PROCESSESxBATCH, e.g. 2x4, got {text!r}") from None
    if procs < 1 or batch < 1:
        raise argparse.ArgumentTypeError(f"processes and batch must be ≥ 1, got {text!r}")
    return procs, batch


def _barrier(folder: Path, name: str, index: int, workers: int, timeout_s: float = 900.0) -> None:
    (folder / f"{name}.{index}").touch()
    start = time.monotonic()
    while sum(1 for _ in folder.glob(f"{name}.*")) < workers:
        if (folder / "abort").exists():
            raise RuntimeError(f"another worker failed (see {folder / 'abort'})")
        if time.monotonic() - start > timeout_s:
            raise TimeoutError(f"barrier {name}: not every worker arrived in {timeout_s:g} s")
        time.sleep(0.01)


def _timed(task: Any, steps: int, gen: torch.Generator, dev: torch.device) -> float:
    start = time.perf_counter()
    res = run_loop(task, LoopConfig(steps, log_every=10**9), gen, "shared")
    sync_device(dev)
    if res.guards.skipped:
        raise FloatingPointError(f"timed steps were skipped: {res.guards.as_dict()}")
    return time.perf_counter() - start


def _window(rig: Rig, stage: str, batch: int, warmup: int, seconds: float, barrier: Any) -> dict[str, Any]:
    """Set up ``batch`` objects of ``stage`` and warm up; at the barriers ``estimate``, ``start`` and
    ``end`` every process estimates its step time, then steps for about ``seconds``. A failure (out
    of memory at a large share) is the row's ``error``; the barriers are still met, so the other
    processes' windows go on."""
    dev = rig.dev
    phases = ["estimate", "start", "end"]
    jobs: list[Any] = []
    try:
        t0 = time.perf_counter()
        jobs = [rig.job(stage, i) for i in range(batch)]
        setup_s = (time.perf_counter() - t0) / batch
        task = jobs[0].task if batch == 1 else BatchTask([j.task for j in jobs], [j.generator for j in jobs])
        gen = torch.Generator().manual_seed(0)
        run_loop(task, LoopConfig(warmup, log_every=10**9), gen, "warmup")
        sync_device(dev)
        if dev.type == "cuda":
            torch.cuda.reset_peak_memory_stats(dev)
        barrier(phases.pop(0))
        # One loop call for the window: a call's fixed cost (a state copy, two evaluated log rows)
        # is then spread over many steps, as in a stage (a log row every 50 steps). n comes from a
        # first estimate made while the other processes make theirs, so all step for about ``seconds``.
        estimate = _timed(task, 3, gen, dev) / 3
        steps = max(3, math.ceil(seconds / max(estimate, 1e-3)))
        barrier(phases.pop(0))
        elapsed = _timed(task, steps, gen, dev)
        barrier(phases.pop(0))
        peak = round(torch.cuda.max_memory_reserved(dev) / 2**30, 2) if dev.type == "cuda" else None
        return {"steps": steps, "elapsed_s": round(elapsed, 3),
                "ms_per_step": round(1000 * elapsed / steps, 2),
                "setup_s_per_object": round(setup_s, 2), "peak_gib": peak}
    except Exception as exc:
        traceback.print_exc()
        for phase in phases:
            barrier(phase)
        return {"error": repr(exc)[:300]}
    finally:
        for j in jobs:
            j.close()
        jobs.clear()
        if dev.type == "cuda":
            torch.cuda.empty_cache()


def parse_mix(text: str) -> tuple[str, int]:
    """``"nerf:4"`` → (stage, objects): one process of a mixed window."""
    stage, _, batch = text.partition(":")
    if stage not in STAGES or not batch.isdigit() or int(batch) < 1:
        raise argparse.ArgumentTypeError(f"a mix entry is STAGE:BATCH with STAGE one of {STAGES}, got {text!r}")
    return stage, int(batch)


Window = tuple[str, list[tuple[int, str, int]]]  # (share name, [(process, stage, batch)])


def plan(shares: list[str], stages: list[str], mix: list[str]) -> list[Window]:
    """Every timed window, the same in every worker: each share at each stage, then (``mix``)
    each mixed process alone and all of them together."""
    windows: list[Window] = []
    for share in shares:
        procs, batch = parse_share(share)
        windows += [(share, [(k, stage, batch) for k in range(procs)]) for stage in stages]
    if mix:
        parts = [parse_mix(m) for m in mix]
        name = "+".join(mix)
        windows += [(f"{name} alone", [(k, stage, batch)]) for k, (stage, batch) in enumerate(parts)]
        windows.append((f"{name} together", [(k, stage, batch) for k, (stage, batch) in enumerate(parts)]))
    return windows


def worker(args: argparse.Namespace) -> int:
    folder, index = args.sync, args.index
    try:
        rig = build_rig(args.device, "after", args.preset, args.scale, args.overrides, args.store,
                        Path(tempfile.mkdtemp(prefix=f"gpu_sharing_{index}_")))
        for needed in STAGES[:-1]:  # the later stages' inputs: short runs, as paper_speed makes them
            measure_stage(rig, needed, 1, 1, 1, False)
        _barrier(folder, "ready", index, args.workers)
        rows: list[dict] = []
        for w, (share, assigned) in enumerate(plan(args.shares, args.stages, args.mix)):
            def barrier(phase: str, w: int = w) -> None:
                _barrier(folder, f"w{w}-{phase}", index, args.workers)
            mine = [(stage, batch) for k, stage, batch in assigned if k == index]
            if mine:
                stage, batch = mine[0]
                row = _window(rig, stage, batch, args.warmup, args.seconds, barrier)
                rows.append({"share": share, "stage": stage, "process": index, "batch": batch, **row})
                print(json.dumps(rows[-1]), flush=True)
                atomic_write_text(args.result, json.dumps(rows, indent=2) + "\n")  # a killed run keeps these
            else:  # idle through this window: its priors stay loaded, its GPU work is none
                for phase in ("estimate", "start", "end"):
                    barrier(phase)
        return 0
    except BaseException:
        (folder / "abort").write_text(traceback.format_exc())
        raise


def mix_efficiency(rows: list[dict], mix: list[str]) -> dict[str, Any] | None:
    """How much of its own alone rate each mixed process kept when all ran together; the sum is the
    GPU's throughput relative to running them one after another (1.0: no gain)."""
    if not mix:
        return None
    name = "+".join(mix)
    kept = {}
    for k, (stage, _batch) in enumerate(parse_mix(m) for m in mix):
        alone = [r for r in rows if r["share"] == f"{name} alone" and r["process"] == k and "error" not in r]
        together = [r for r in rows if r["share"] == f"{name} together" and r["process"] == k and "error" not in r]
        if not alone or not together:
            return {"mix": name, "error": f"process {k} ({stage}) has no alone and together rows"}
        kept[f"{k}:{stage}"] = round(alone[0]["ms_per_step"] / together[0]["ms_per_step"], 3)
    return {"mix": name, "kept": kept, "throughput_vs_one_after_another": round(sum(kept.values()), 3)}


def aggregate(rows: list[dict], schedule: dict[str, int]) -> tuple[list[dict], list[dict]]:
    """Per (share, stage): the object-steps per second of all its processes together; per share:
    minutes per object and objects per GPU-hour over the whole schedule."""
    stages, shares = [], []
    for share in dict.fromkeys(r["share"] for r in rows):
        per_stage = {}
        for stage in dict.fromkeys(r["stage"] for r in rows if r["share"] == share):
            mine = [r for r in rows if r["share"] == share and r["stage"] == stage]
            if any("error" in r for r in mine):
                per_stage[stage] = {"share": share, "stage": stage, "processes": len(mine),
                                    "error": next(r["error"] for r in mine if "error" in r)}
                stages.append(per_stage[stage])
                continue
            rate = sum(r["batch"] * r["steps"] / r["elapsed_s"] for r in mine)  # object-steps per second
            setup = sum(r["setup_s_per_object"] for r in mine) / len(mine)
            per_stage[stage] = {"share": share, "stage": stage, "processes": len(mine),
                                "ms_per_step_each": [r["ms_per_step"] for r in mine],
                                "ms_per_object_step": round(1000 / rate, 2), "setup_s_per_object": round(setup, 2),
                                "peak_gib_sum": round(sum(r["peak_gib"] or 0.0 for r in mine), 2) or None}
            stages.append(per_stage[stage])
        if set(per_stage) == set(STAGES) and not any("error" in v for v in per_stage.values()):
            # GPU time per object: the aggregate rate; set-up runs in the processes in parallel too.
            gpu_min = sum(per_stage[s]["ms_per_object_step"] * schedule[s] / 60000 for s in STAGES)
            gpu_min += sum(per_stage[s]["setup_s_per_object"] for s in STAGES) / 60 / per_stage[STAGES[0]]["processes"]
            shares.append({"share": share, "gpu_min_per_object": round(gpu_min, 2),
                           "objects_per_gpu_hour": round(60 / gpu_min, 2),
                           "peak_gib": max(per_stage[s]["peak_gib_sum"] or 0.0 for s in STAGES) or None})
    return stages, shares


def to_markdown(res: dict) -> str:
    base = {r["stage"]: r["ms_per_object_step"] for r in res["stages"]
            if r["share"] == res["stages"][0]["share"] and "error" not in r}
    lines = [f"# Several runs on one GPU — {res['device']}, {res['date']}", "",
             f"torch {res['torch']}; preset `{res['preset']}`, priors `{res['scale']}` (random weights), mode `after`; "
             f"per (share, stage): {res['warmup']} warm-up steps, then about {res['seconds']} s of steps in every "
             f"process at once (one loop call of n steps, n from a first estimate). "
             f"Command: `{res['command']}`.", "",
             "Share `PxB`: P processes on the GPU, B objects in each one's batch. The aggregate ms per object-step "
             "is 1000 / (object-steps per second of all P together); `vs first` compares it with the first share "
             "(same stage, same call).", "",
             "| share | stage | ms/step of each process | aggregate ms per object-step | vs first | peak GiB (sum) |",
             "|---|---|---|---:|---:|---:|"]
    for r in res["stages"]:
        if "error" in r:
            lines.append(f"| {r['share']} | {r['stage']} | error: {r['error'][:120]} | | | |")
            continue
        ratio = base.get(r["stage"], r["ms_per_object_step"]) / r["ms_per_object_step"]
        lines.append(f"| {r['share']} | {r['stage']} | {', '.join(f'{v:g}' for v in r['ms_per_step_each'])} | "
                     f"{r['ms_per_object_step']} | {ratio:.2f}× | {r['peak_gib_sum']} |")
    sched = res["schedule"]
    lines += ["", f"Whole schedule ({sched['nerf']} + {sched['dmtet']} + {sched['texture']} steps), GPU minutes per "
              "object from the aggregate rates (each object's own run takes P times as long):", "",
              "| share | GPU min per object | objects / GPU-hour | peak GiB (all processes) |", "|---|---:|---:|---:|"]
    for s in res["shares"]:
        lines.append(f"| {s['share']} | {s['gpu_min_per_object']} | **{s['objects_per_gpu_hour']}** | "
                     f"{s['peak_gib']} |")
    mix = res.get("mix")
    if mix and "error" not in mix:
        kept = ", ".join(f"{k} {v:.2f}" for k, v in mix["kept"].items())
        lines += ["", f"Mixed stages `{mix['mix']}`: each process kept this share of its own alone rate when all "
                  f"ran together: {kept}; sum **{mix['throughput_vs_one_after_another']:.2f}×** the throughput of "
                  "running them one after another."]
    elif mix:
        lines += ["", f"Mixed stages `{mix['mix']}`: {mix['error']}"]
    if res.get("errors"):
        lines += ["", "Errors: " + "; ".join(res["errors"])]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda")
    p.add_argument("--preset", default="paper")
    p.add_argument("--scale", default="full", choices=["full", "tiny"])
    p.add_argument("--shares", nargs="*", default=["1x8", "2x4", "2x8"], help="PROCESSESxBATCH, the first is the base")
    p.add_argument("--mix", nargs="*", default=[], metavar="STAGE:BATCH",
                   help="processes in different stages: each timed alone, then all together")
    p.add_argument("--stages", nargs="+", default=list(STAGES), choices=STAGES)
    p.add_argument("--seconds", type=float, default=20.0)
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--store", type=Path, default=ROOT / "outputs" / "gpu_refs")
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    p.add_argument("--tag", default="cpu")
    p.add_argument("--budget-s", type=float, default=None,
                   help="stop the workers after this long and report what they made")
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--index", type=int, default=0, help=argparse.SUPPRESS)
    p.add_argument("--workers", type=int, default=1, help=argparse.SUPPRESS)
    p.add_argument("--sync", type=Path, help=argparse.SUPPRESS)
    p.add_argument("--result", type=Path, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    windows = plan(args.shares, args.stages, args.mix)  # bad shares or mix entries fail here, before any worker
    if args.worker:
        return worker(args)

    t_start = time.perf_counter()
    prepare_references(args.store, preset(args.preset, ["device=cpu"]))  # once, before the workers read them
    workers = max(len(assigned) for _, assigned in windows)
    sync = Path(tempfile.mkdtemp(prefix="gpu_sharing_sync_"))
    passed = list(argv if argv is not None else sys.argv[1:])
    procs = [subprocess.Popen([sys.executable, "-m", "benchmarks.gpu_sharing", *passed, "--worker",
                               "--index", str(k), "--workers", str(workers), "--sync", str(sync),
                               "--result", str(sync / f"rows.{k}.json")],
                              cwd=ROOT, env={**os.environ, "PYTHONUNBUFFERED": "1"}) for k in range(workers)]
    deadline = None if args.budget_s is None else t_start + args.budget_s
    while any(proc.poll() is None for proc in procs) and (deadline is None or time.perf_counter() < deadline):
        time.sleep(0.5)
    for proc in procs:
        if proc.poll() is None:
            proc.kill()
    codes = [proc.wait() for proc in procs]
    rows, errors = [], []
    for k, code in enumerate(codes):
        result = sync / f"rows.{k}.json"
        if result.exists():
            rows += json.loads(result.read_text())
        if code != 0:
            errors.append(f"worker {k} exited {code}" + (" (stopped at --budget-s)" if code == -9 else ""))
    if (sync / "abort").exists():
        errors.append((sync / "abort").read_text().strip().splitlines()[-1])
    cfg = preset(args.preset)
    schedule = {"nerf": cfg.nerf.loop.steps, "dmtet": cfg.dmtet.loop.steps, "texture": cfg.texture.loop.steps}
    stages, shares = aggregate(rows, schedule)
    dev = torch.device(args.device)
    name = (subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True,
                           text=True).stdout.strip().splitlines() or ["GPU"])[0] if dev.type == "cuda" \
        else platform.processor() or platform.machine()
    res = {"date": datetime.now(timezone.utc).strftime("%Y-%m-%d"), "device": name, "torch": torch.__version__,
           "preset": args.preset, "scale": args.scale, "warmup": args.warmup, "seconds": args.seconds,
           "schedule": schedule, "rows": rows, "stages": stages, "shares": shares,
           "mix": mix_efficiency(rows, args.mix), "errors": errors,
           "wall_s": round(time.perf_counter() - t_start, 1),
           "command": "python -m benchmarks.gpu_sharing " + " ".join(passed)}
    args.out.mkdir(parents=True, exist_ok=True)
    stem = args.out / f"gpu_sharing_{args.tag}"
    atomic_write_text(stem.with_suffix(".json"), json.dumps(res, indent=2) + "\n")
    atomic_write_text(stem.with_suffix(".md"), to_markdown(res))
    print(to_markdown(res))
    return 0 if not errors else 1


if __name__ == "__main__":
    raise SystemExit(main())
