"""Where a stage step's host time goes: torch-function calls per source file, counted on the CPU.

A launch-bound step costs host time per torch call, whatever the device, so the count of calls per
file of one step (ops, tensor methods and property reads, through a ``TorchFunctionMode``) says
which code to fuse or compile first. The priors are eager on the CPU but CUDA-graph replays on the
GPU: their files are listed, and left out of the "without priors" share. Backward ops are not
Python calls and are not counted.

    python -m benchmarks.op_census --stage dmtet --work outputs/op_census   # paper preset, tiny priors

The earlier stages run one step each to make the stage's input (kept in ``--work``: a second run
starts at the stage asked for).
"""

from __future__ import annotations

import argparse
import collections
import json
import platform
import sys
import traceback
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import torch
from torch.overrides import TorchFunctionMode

from assets_store.atomic import atomic_write_text
from benchmarks.paper_speed import ROOT, STAGES, build_rig
from ops.engine.loop import GuardCounters, LoopConfig, LoopResult, run_loop

PRIOR_FILES = ("morpheus_core/priors/", "morpheus_core/diffusion.py", "morpheus_core/guidance.py")


class CallCensus(TorchFunctionMode):
    """Counts torch-function calls by the innermost repository file that made them."""

    def __init__(self) -> None:
        super().__init__()
        self.files: collections.Counter[str] = collections.Counter()

    def __torch_function__(self, func: Any, types: Any, args: tuple = (), kwargs: dict | None = None) -> Any:
        root = f"{ROOT}/"
        frames = [f.filename for f in traceback.extract_stack()[:-1]
                  if f.filename.startswith(root) and "/.venv/" not in f.filename and "/benchmarks/" not in f.filename]
        self.files[frames[-1][len(root):] if frames else "(outside the repository)"] += 1
        return func(*args, **(kwargs or {}))


def census(stage: str, steps: int, work: Path) -> dict[str, Any]:
    work.mkdir(parents=True, exist_ok=True)
    rig = build_rig("cpu", "after", "paper", "tiny", [], ROOT / "outputs" / "gpu_refs", work)
    for earlier in STAGES[:STAGES.index(stage)]:
        out = work / f"{earlier}_0"
        if not (out / "done").exists():
            job = rig.job(earlier, 0)
            try:
                run_loop(job.task, LoopConfig(1, log_every=10**9), torch.Generator().manual_seed(0), "input")
                job.finish(LoopResult([], GuardCounters(), None, 0, 0.0))
            finally:
                job.close()
            atomic_write_text(out / "done", "")
        setattr(rig, f"{earlier}_dir", out)
    job = rig.job(stage, 0)
    try:
        gen = torch.Generator().manual_seed(0)
        run_loop(job.task, LoopConfig(1, log_every=10**9), gen, "warmup")
        counter = CallCensus()
        with counter:
            run_loop(job.task, LoopConfig(steps, log_every=10**9), gen, "census")
    finally:
        job.close()
    per_step = {k: v / steps for k, v in counter.files.most_common()}
    total = sum(per_step.values())
    priors = sum(v for k, v in per_step.items() if k.startswith(PRIOR_FILES))
    return {"stage": stage, "steps": steps, "calls_per_step": round(total),
            "calls_per_step_without_priors": round(total - priors),
            "files": [{"file": k, "calls_per_step": v, "share_without_priors":
                       None if k.startswith(PRIOR_FILES) else round(v / max(total - priors, 1), 3)}
                      for k, v in per_step.items()]}


def to_markdown(res: dict[str, Any]) -> str:
    lines = [f"# Torch-function calls per {res['stage']} step, by file — {res['machine']}, {res['date']}", "",
             f"Command: `{res['command']}`. Paper preset, tiny priors on the CPU, {res['steps']} steps counted "
             f"after one. {res['calls_per_step']} calls a step, {res['calls_per_step_without_priors']} without "
             "the priors (CUDA-graph replays on the GPU).", "",
             "| file | calls per step | share without priors |", "|---|---:|---:|"]
    for row in res["files"][:30]:
        share = "prior" if row["share_without_priors"] is None else f"{100 * row['share_without_priors']:.1f} %"
        lines.append(f"| `{row['file']}` | {row['calls_per_step']:.0f} | {share} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--stage", choices=STAGES, default="dmtet")
    p.add_argument("--steps", type=int, default=2)
    p.add_argument("--work", type=Path, default=ROOT / "outputs" / "op_census")
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    args = p.parse_args(argv)
    res = census(args.stage, args.steps, args.work)
    res |= {"machine": f"{platform.node() or 'cpu'} (CPU), torch {torch.__version__}",
            "date": datetime.now(timezone.utc).strftime("%Y-%m-%d"),
            "command": "python -m benchmarks.op_census " + " ".join(sys.argv[1:] if argv is None else argv)}
    stem = args.out / f"op_census_{args.stage}_cpu"
    atomic_write_text(stem.with_suffix(".json"), json.dumps(res, indent=1))
    atomic_write_text(stem.with_suffix(".md"), to_markdown(res))
    print(to_markdown(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
