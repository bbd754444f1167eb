"""Resume on the GPU: a run killed with SIGKILL mid-stage resumes from its checkpoint and ends within
the seed spread of an uninterrupted run.

On the CPU a resumed run is bit-identical to an uninterrupted one (``tests/test_resume.py``); on CUDA
the kernels' atomics reorder floating-point sums, so the two runs part after the restart and the
question is whether the asset is as good. Per (scene, seed): a child process runs the scene through
the pipeline with the oracle priors (``benchmarks/early_stop.py``'s fixed schedule) and is killed
with SIGKILL once the chosen stage has checkpointed a random step of its first or second half; a
second child resumes it to the end. The resumed GLB's novel-view PSNR is set against the
uninterrupted run's (the records of ``early_stop.py``, same schedule, scene and seed) and against
the seed spread of those records (the range over seeds).

    python -m benchmarks.gpu_resume --device cuda \\
        --records benchmarks/results/schedule_quality_h200_stochastic.records.jsonl \\
        --schedule fast/20 --scenes mug,tin --seed 0 --stage nerf --name gpu_resume_h200
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from benchmarks.early_stop import BASES, RESULTS, oracle_work, variant_schedule
from benchmarks.error_time import run_error_time
from benchmarks.oracle import OracleConfig
from benchmarks.quality import SIZES, machine, write_results
from benchmarks.scene_runs import photo_path, schedule_store
from benchmarks.scenes import make_scenes

ROOT = Path(__file__).resolve().parent.parent


def checkpointed_step(work: Path, label: str, scene: str, stage: str) -> int:
    """The latest step ``stage`` has checkpointed in the run's store (-1: none yet)."""
    store = schedule_store(oracle_work(work, OracleConfig()), _schedule(label))
    steps = [int(p.stem.split("-")[1]) for p in store.checkpoint_dir(scene, stage).glob("**/step-*.ckpt")]
    return max(steps, default=-1)


def _schedule(label: str) -> Any:
    """``<schedule>:<seed>`` as the fixed-schedule variant ``early_stop.py`` runs."""
    base, seed = label.rsplit(":", 1)
    return variant_schedule(BASES[base], int(seed), False)


def child(args: argparse.Namespace) -> int:
    """Run one scene to the end (resuming from whatever the store holds); its record as JSON on stdout."""
    scene = make_scenes(0, [args.scene])[0]
    work = oracle_work(args.work, OracleConfig())
    photo_path(scene, work / "photos")
    rec = run_error_time([scene], [_schedule(f"{args.schedule}:{args.seed}")], args.device, work,
                         SIZES["gpu" if args.device == "cuda" else "cpu"].eval, OracleConfig())[0]
    print("RECORD " + json.dumps(rec, default=str), flush=True)
    return 0


def _child_cmd(args: argparse.Namespace, scene: str) -> list[str]:
    return [sys.executable, "-m", "benchmarks.gpu_resume", "--child", "--device", args.device, "--work",
            str(args.work), "--schedule", args.schedule, "--seed", str(args.seed), "--scene", scene]


def kill_and_resume(args: argparse.Namespace, scene: str, rng: random.Random) -> dict[str, Any]:
    label = f"{args.schedule}:{args.seed}"
    cfg = _schedule(label).config(args.device)
    steps = getattr(cfg, args.stage).loop.steps
    every = getattr(cfg, args.stage).loop.checkpoint_every
    kill_at = rng.choice([s for s in range(every, steps, every)] or [every])
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    proc = subprocess.Popen(_child_cmd(args, scene), env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + args.timeout
    while proc.poll() is None and checkpointed_step(args.work, label, scene, args.stage) < kill_at:
        if time.monotonic() > deadline:
            proc.kill()
            raise TimeoutError(f"{scene}: {args.stage} did not checkpoint step {kill_at} in {args.timeout} s")
        time.sleep(0.2)
    if proc.poll() is not None:
        raise RuntimeError(f"{scene}: the run ended (exit {proc.returncode}) before {args.stage} reached {kill_at}")
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    resumed_from = checkpointed_step(args.work, label, scene, args.stage)
    done = subprocess.run(_child_cmd(args, scene), env=env, capture_output=True, text=True, timeout=args.timeout)
    lines = [ln for ln in done.stdout.splitlines() if ln.startswith("RECORD ")]
    if done.returncode or not lines:
        raise RuntimeError(f"{scene}: the resumed run failed (exit {done.returncode}): {done.stderr[-2000:]}")
    rec = json.loads(lines[-1][len("RECORD "):])
    return {"scene": scene, "killed_in": args.stage, "killed_after_step": resumed_from, "stage_steps": steps,
            "glb_psnr": rec["points"][-1]["novel_psnr"], "fscore": rec["points"][-1]["fscore"]}


def judge(run: dict[str, Any], records: list[dict[str, Any]], schedule: str, seed: int) -> dict[str, Any]:
    """The resumed run against the uninterrupted one (same schedule, scene, seed) and the seed spread."""
    same = [r for r in records if r.get("base") == schedule and r.get("scene") == run["scene"] and "points" in r
            and not r.get("early_stop")]
    glb = {r["seed"]: r["points"][-1]["novel_psnr"] for r in same}
    if seed not in glb:
        return {**run, "uninterrupted_psnr": None, "delta": None, "spread": None, "within": None}
    spread = max(glb.values()) - min(glb.values()) if len(glb) > 1 else None
    delta = run["glb_psnr"] - glb[seed]
    return {**run, "uninterrupted_psnr": glb[seed], "delta": delta, "spread": spread,
            "within": None if spread is None else abs(delta) <= spread}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--scene", help=argparse.SUPPRESS)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--schedule", default="fast/20", choices=sorted(BASES))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scenes", default="mug,tin")
    ap.add_argument("--stage", default="nerf", choices=("nerf", "dmtet", "texture"))
    ap.add_argument("--records", type=Path, nargs="*", default=[], help="early_stop records of uninterrupted runs")
    ap.add_argument("--work", type=Path, default=Path("outputs/gpu_resume"))
    ap.add_argument("--timeout", type=float, default=400.0)
    ap.add_argument("--name", default="gpu_resume")
    ap.add_argument("--results", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    if args.child:
        return child(args)
    records = [json.loads(line) for f in args.records for line in f.read_text().splitlines() if line]
    rng = random.Random(args.seed)
    runs = []
    for scene in args.scenes.split(","):
        try:
            runs.append(judge(kill_and_resume(args, scene, rng), records, args.schedule, args.seed))
        except (RuntimeError, TimeoutError) as exc:
            runs.append({"scene": scene, "error": str(exc)[:500]})
        print(json.dumps(runs[-1]), flush=True)
    lines = ["| scene | killed in | after step | GLB PSNR resumed | uninterrupted | Δ | seed spread | within |",
             "|---|---|---:|---:|---:|---:|---:|---|"]
    for r in runs:
        if "error" in r:
            lines.append(f"| {r['scene']} | error: {r['error'][:200]} | | | | | | |")
            continue
        fmt = (lambda v, f: "–" if v is None else format(v, f))  # noqa: E731
        lines.append(f"| {r['scene']} | {r['killed_in']} | {r['killed_after_step']} of {r['stage_steps']} | "
                     f"{r['glb_psnr']:.2f} | {fmt(r['uninterrupted_psnr'], '.2f')} | {fmt(r['delta'], '+.2f')} | "
                     f"{fmt(r['spread'], '.2f')} | {r['within']} |")
    write_results(args.results, args.name, {
        "title": "Resume on the GPU after SIGKILL", "machine": machine(args.device), "wall_s": 0.0,
        "date": time.strftime("%Y-%m-%d"), "schedule": args.schedule, "seed": args.seed, "runs": runs,
        "command": "python -m benchmarks.gpu_resume " + " ".join(argv if argv is not None else sys.argv[1:]),
        "about": __doc__.split("\n\n")[1].replace("\n", " ")}, "\n".join(lines) + "\n")
    return 0 if all("error" not in r for r in runs) else 1


if __name__ == "__main__":
    raise SystemExit(main())
