"""Time per guidance step with the real prior code on full-size architectures (random weights).

Two steps are timed, each for several objects per batch and each acceleration path:
- ``zero123_sds``: render 256 px → VAE encode → Zero123 ε with CFG 3 (the 3D SDS of stage 1),
  backward to the render;
- ``stage2``: render 512 px → both priors: Zero123 SDS full-pass + 2D prior (SD1.5 + canny
  ControlNet + IP-Adapter, CFG 2) VSD high-pass with one LoRA per object (ε_φ forward and the
  ε-MSE update), backward to the render, Adam step on the adapters (``stage2_texture``).
Weights are random (compute does not depend on their values): nothing is downloaded. The eager
one-object anchors of DESIGN.md §7 are the reference; the target is ≥ 3× less time per object.

    python benchmarks/prior_speed.py                  # CUDA, full size: ~3-5 min on an H200
    python benchmarks/prior_speed.py --quick          # fewer batches/steps
    python benchmarks/prior_speed.py --tiny           # CPU smoke run of the same code path
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
import traceback
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import torch

from assets_store.atomic import atomic_write_text
from benchmarks.timing import sync_device
from morpheus_core.guidance.diffusion import NoiseSchedule
from morpheus_core.guidance.hybrid import PriorBinding, hybrid_guidance
from morpheus_core.guidance.presets import PRIOR_2D, PRIOR_3D, stage1_dmtet, stage2_texture
from morpheus_core.priors.architectures import image2d_parts, zero123_parts
from morpheus_core.priors.image2d import Image2DPrior
from morpheus_core.priors.image_prompt import IPAdapterEncoder
from morpheus_core.priors.lora import ObjectLoras
from morpheus_core.priors.runtime import PriorRuntime
from morpheus_core.priors.zero123 import Zero123Prior

# DESIGN.md §7, H200, eager fp16, one object (ms): the blocks each step is made of.
ANCHOR_BLOCKS = {"zero123_cfg": 24.0, "sd_controlnet_cfg": 37.0, "lora_fwd_bwd": 73.0, "vae256_fwd_bwd": 8.0,
                 "vae512_fwd_bwd": 24.0}
ANCHORS_MS = {
    "zero123_sds": ANCHOR_BLOCKS["zero123_cfg"] + ANCHOR_BLOCKS["vae256_fwd_bwd"],
    "stage2": sum(ANCHOR_BLOCKS[k] for k in ("zero123_cfg", "vae256_fwd_bwd", "sd_controlnet_cfg", "lora_fwd_bwd",
                                             "vae512_fwd_bwd")),
}
DTYPES = {"fp16": torch.float16, "bf16": torch.bfloat16, "fp32": torch.float32}


@dataclass
class Rig:
    zero123: Zero123Prior
    image2d: Image2DPrior | None
    loras: ObjectLoras | None


def build_priors(scale: str, runtime: PriorRuntime, n_objects: int, with_2d: bool, seed: int = 0) -> Rig:
    """A ``Rig`` of fresh random priors on the device, with references for ``n_objects`` objects (built there
    directly: fast even at full size)."""
    with torch.device(runtime.device):
        z = zero123_parts(scale, seed)
        zero123 = Zero123Prior(z.unet, z.vae, z.image_encoder, z.image_processor, z.projection, runtime)
        image2d = loras = None
        if with_2d:
            p = image2d_parts(scale, seed + 1)
            g = torch.Generator(device=runtime.device).manual_seed(seed)
            # The empty-prompt context would come from the SD text encoder; random of the same shape here.
            null_context = torch.randn(1, 77, p.unet.config.cross_attention_dim, generator=g, device=runtime.device)
            encoder = IPAdapterEncoder(p.image_encoder, p.image_processor, null_context, p.ip_adapter_state, runtime)
            image2d = Image2DPrior(p.unet, p.controlnet, p.vae, encoder, runtime)
            loras = ObjectLoras(image2d)
    g = torch.Generator().manual_seed(seed)
    for i in range(n_objects):
        photo = torch.rand(4, 256, 256, generator=g)
        zero123.set_reference(f"obj{i}", photo)
        if image2d is not None:
            image2d.set_reference(f"obj{i}", photo)
            loras.add(f"obj{i}")
    return Rig(zero123, image2d, loras)


def _step_fn(kind: str, rig: Rig, batch: int, device: str, schedule: NoiseSchedule):
    ids = [f"obj{i}" for i in range(batch)]
    g = torch.Generator().manual_seed(1)
    res = 256 if kind == "zero123_sds" else 512
    render = torch.rand(batch, 3, res, res, generator=g).to(device).requires_grad_(True)
    elev = torch.empty(batch).uniform_(-45, 45, generator=g)
    azim = torch.empty(batch).uniform_(-180, 180, generator=g)
    config = stage1_dmtet() if kind == "zero123_sds" else stage2_texture()
    step_gen = torch.Generator().manual_seed(2)

    def step(i: int) -> None:
        render.grad = None
        bindings = {PRIOR_3D: PriorBinding(rig.zero123, condition=rig.zero123.condition(ids, elev, azim))}
        if kind == "stage2":
            bindings[PRIOR_2D] = PriorBinding(rig.image2d, rig.loras, rig.image2d.condition(ids, render))
        out = hybrid_guidance(config, bindings, schedule, render, i, generator=step_gen)
        (out.loss + out.finetune_loss).backward()
        if rig.loras is not None and kind == "stage2":
            rig.loras.step()
        if not bool(torch.isfinite(render.grad).all()):
            raise FloatingPointError("non-finite gradient on the render")

    return step


def measure(kind: str, rig: Rig, batch: int, device: str, warmup: int, steps: int) -> dict:
    schedule = NoiseSchedule()
    step = _step_fn(kind, rig, batch, device, schedule)
    if torch.device(device).type == "cuda":
        torch.cuda.reset_peak_memory_stats()
    for i in range(warmup):
        step(i)
    times = []
    for i in range(steps):
        sync_device(device)
        t0 = time.perf_counter()
        step(warmup + i)
        sync_device(device)
        times.append((time.perf_counter() - t0) * 1e3)
    med = statistics.median(times)
    row = {"median_ms": round(med, 2), "ms_per_object": round(med / batch, 2), "min_ms": round(min(times), 2),
           "steps": steps}
    if torch.device(device).type == "cuda":
        row["peak_gib"] = round(torch.cuda.max_memory_allocated() / 2**30, 2)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results"))
    parser.add_argument("--tag", default=None, help="result file suffix (default: h200/cuda/cpu_tiny)")
    parser.add_argument("--tiny", action="store_true", help="tiny architectures (CPU smoke run)")
    parser.add_argument("--quick", action="store_true", help="batches 1 and 8, fewer steps")
    parser.add_argument("--batches", type=int, nargs="+", default=None)
    parser.add_argument("--modes", nargs="+", default=None, choices=["eager", "cudagraph", "compile"])
    parser.add_argument("--kinds", nargs="+", default=["zero123_sds", "stage2"], choices=["zero123_sds", "stage2"])
    parser.add_argument("--dtype", default="fp16", choices=sorted(DTYPES))
    parser.add_argument("--warmup", type=int, default=None)
    parser.add_argument("--steps", type=int, default=None)
    parser.add_argument("--vae-dtype", default=None, choices=sorted(DTYPES),
                        help="VAE precision (default: fp32 under fp16, else the prior dtype)")
    parser.add_argument("--profile", action="store_true",
                        help="also write a torch.profiler table of 3 steps per row to <out>/prior_profile_<tag>.txt")
    args = parser.parse_args()

    cuda = torch.cuda.is_available()
    if not cuda and not args.tiny:
        parser.error("full-size architectures need CUDA; use --tiny for a CPU run")
    device = "cuda" if cuda else "cpu"
    scale = "tiny" if args.tiny else "full"
    dtype = DTYPES[args.dtype] if cuda else torch.float32
    modes = args.modes or (["eager", "cudagraph"] if cuda else ["eager"])
    batches = args.batches or ([1, 8] if args.quick else [1, 4, 8])
    if args.tiny and not args.batches:
        batches = [1, 2]
    warmup = args.warmup if args.warmup is not None else (2 if args.quick or args.tiny else 3)
    steps = args.steps if args.steps is not None else (2 if args.tiny else 6 if args.quick else 15)
    if cuda:
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True

    rows: list[dict] = []
    profiles: list[str] = []
    t_start = time.perf_counter()
    for mode in modes:
        vae_dtype = DTYPES[args.vae_dtype] if args.vae_dtype else None
        runtime = PriorRuntime(device, dtype, vae_dtype=vae_dtype, channels_last=cuda, accel=mode)
        for kind in args.kinds:
            rig = None
            try:
                rig = build_priors(scale, runtime, max(batches), with_2d=kind == "stage2")
            except Exception as exc:  # one failing configuration must not stop the others
                rows += [{"kind": kind, "mode": mode, "batch": b, "error": f"build: {exc!r}"} for b in batches]
                traceback.print_exc()
            for b in batches if rig is not None else []:
                row = {"kind": kind, "mode": mode, "batch": b, "dtype": str(dtype).replace("torch.", "")}
                try:
                    row |= measure(kind, rig, b, device, warmup, steps)
                    if args.profile:
                        profiles.append(f"## {kind} {mode} batch {b}\n{profile_table(kind, rig, b, device)}")
                    row["speedup_per_object_vs_anchor"] = round(ANCHORS_MS[kind] / row["ms_per_object"], 2)
                except Exception as exc:
                    row["error"] = repr(exc)[:500]
                    traceback.print_exc()
                rows.append(row)
                print(json.dumps(row), flush=True)
            del rig
            if cuda:
                torch.cuda.empty_cache()

    name = torch.cuda.get_device_name(0) if cuda else (platform.processor() or platform.machine())
    summary = {
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d"), "device": name, "torch": torch.__version__,
        "cuda": torch.version.cuda, "scale": scale, "warmup": warmup, "steps": steps,
        "anchors_ms_per_object": ANCHORS_MS, "anchor_blocks_ms": ANCHOR_BLOCKS,
        "total_wall_s": round(time.perf_counter() - t_start, 1), "rows": rows,
    }
    tag = args.tag or ("cpu_tiny" if not cuda else ("h200" if "H200" in name else "cuda") + ("_tiny" if args.tiny
                                                                                              else ""))
    if profiles:
        atomic_write_text(args.out / f"prior_profile_{tag}.txt", "\n\n".join(profiles) + "\n")
    atomic_write_text(args.out / f"prior_speed_{tag}.json", json.dumps(summary, indent=2))
    atomic_write_text(args.out / f"prior_speed_{tag}.md", _markdown(summary))
    print(f"wrote {args.out}/prior_speed_{tag}.{{json,md}} in {summary['total_wall_s']} s")


def profile_table(kind: str, rig: Rig, batch: int, device: str, rows: int = 30) -> str:
    """Where one step's time goes: the top operators by device (or CPU) self time over 3 steps."""
    from torch.profiler import ProfilerActivity, profile

    step = _step_fn(kind, rig, batch, device, NoiseSchedule())
    step(0)
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if torch.device(device).type == "cuda" else [])
    with profile(activities=activities) as prof:
        for i in range(3):
            step(1 + i)
        sync_device(device)
    key = "self_cuda_time_total" if torch.device(device).type == "cuda" else "self_cpu_time_total"
    return prof.key_averages().table(sort_by=key, row_limit=rows, max_name_column_width=60)


def _markdown(s: dict) -> str:
    lines = [f"# Prior guidance step speed ({s['scale']} architectures, random weights)", "",
             f"Device: {s['device']}; torch {s['torch']} (CUDA {s['cuda']}); date {s['date']}; "
             f"{s['warmup']} warm-up + {s['steps']} timed steps per row; total {s['total_wall_s']} s.", "",
             "Anchors (DESIGN.md §7, eager fp16, one object): Zero123 SDS step = Zero123 CFG forward 24 + VAE 256 "
             f"fwd+bwd 8 = {s['anchors_ms_per_object']['zero123_sds']:.0f} ms; stage-2 step = that + SD/ControlNet "
             f"CFG 37 + LoRA fwd+bwd 73 + VAE 512 24 = {s['anchors_ms_per_object']['stage2']:.0f} ms. "
             "Target: ≥ 3× less per object.", "",
             "| step | mode | objects | median ms/step | ms/object | × vs anchor | peak GiB | note |",
             "|---|---|---:|---:|---:|---:|---:|---|"]
    for r in s["rows"]:
        if "error" in r:
            lines.append(f"| {r['kind']} | {r['mode']} | {r['batch']} | – | – | – | – | {r['error'][:80]} |")
        else:
            lines.append(f"| {r['kind']} | {r['mode']} | {r['batch']} | {r['median_ms']:.1f} | "
                         f"{r['ms_per_object']:.1f} | {r['speedup_per_object_vs_anchor']:.2f} | "
                         f"{r.get('peak_gib', '–')} | |")
    if s["scale"] == "tiny":
        lines += ["", "Tiny architectures: a smoke run of the code path; these times say nothing about the GPU."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
