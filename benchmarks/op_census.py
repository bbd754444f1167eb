"""Where a stage step's host time goes: torch-function calls per source file, counted on the CPU.

A launch-bound step costs host time per torch call, whatever the device, so the count of calls per
file of one step (ops, tensor methods and property reads, through a ``TorchFunctionMode``) says
which code to fuse or compile first. The priors are eager on the CPU but CUDA-graph replays on the
GPU: their files are listed, and left out of the "without priors" share. Backward ops are not
Python calls and are not counted.

It also lists the **host reads** per step by line: the calls that on CUDA wait for the device
(a value read to the host, or an output whose size depends on the data). The CPU has no such wait,
so this is the CPU's view of what CUDA's sync debug mode reports (``paper_speed.py --profile``): it
lets a session without a GPU see which syncs a change removes.

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
# Calls that read a device value on the host, or whose output size is data-dependent.
_HOST_READS = {"tolist", "item", "__bool__", "__int__", "__float__", "__index__", "numpy", "cpu", "nonzero",
               "argwhere", "unique", "unique_consecutive", "masked_select", "_unique2"}


def _is_host_read(func: Any, args: tuple, kwargs: dict) -> bool:
    name = getattr(func, "__name__", "")
    if name in _HOST_READS:
        return True
    if name == "repeat_interleave":  # tensor repeats without output_size: the total is read
        repeats = args[1] if len(args) > 1 else kwargs.get("repeats")
        return isinstance(repeats, torch.Tensor) and repeats.numel() > 1 and kwargs.get("output_size") is None
    if name in ("__getitem__", "index_put", "index_put_", "__setitem__"):  # a boolean-mask index
        index = args[1] if len(args) > 1 else None
        parts = index if isinstance(index, tuple | list) else (index,)
        return any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in parts)
    return False


class CallCensus(TorchFunctionMode):
    """Counts torch-function calls by the innermost repository file that made them."""

    def __init__(self) -> None:
        super().__init__()
        self.files: collections.Counter[str] = collections.Counter()
        self.host_reads: collections.Counter[str] = collections.Counter()

    def __torch_function__(self, func: Any, types: Any, args: tuple = (), kwargs: dict | None = None) -> Any:
        root = f"{ROOT}/"
        frames = [f for f in traceback.extract_stack()[:-1]
                  if f.filename.startswith(root) and "/.venv/" not in f.filename and "/benchmarks/" not in f.filename]
        self.files[frames[-1].filename[len(root):] if frames else "(outside the repository)"] += 1
        kwargs = kwargs or {}
        if _is_host_read(func, args, kwargs):
            site = f"{frames[-1].filename[len(root):]}:{frames[-1].lineno}" if frames else "(outside the repository)"
            self.host_reads[f"{site} {getattr(func, '__name__', func)}"] += 1
        return func(*args, **kwargs)


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
    reads = {k: v / steps for k, v in counter.host_reads.most_common()}
    return {"stage": stage, "steps": steps, "calls_per_step": round(total),
            "host_reads_per_step": round(sum(reads.values()), 1),
            "host_reads_without_priors": round(sum(v for k, v in reads.items() if not k.startswith(PRIOR_FILES)), 1),
            "host_read_sites": [{"site": k, "per_step": v} for k, v in reads.items()],
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
    lines += ["", f"Host reads per step (syncs on CUDA): {res['host_reads_per_step']}, "
              f"{res['host_reads_without_priors']} without the priors.", "",
              "| site | call | per step |", "|---|---|---:|"]
    for row in res["host_read_sites"][:30]:
        site, call = row["site"].rsplit(" ", 1)
        lines.append(f"| `{site}` | {call} | {row['per_step']:g} |")
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
