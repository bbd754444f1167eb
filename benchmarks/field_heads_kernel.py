"""The fused field-head kernels (``morpheus_core/geometry/mlp_triton.py``) against the modules, and
a sweep of their launch sizes (rows per program, warps, backward programs per SM), of how the
backward sums the weight gradients (``mlp_triton._WEIGHT_GRADS``) and of how its two heads meet in
the feature gradient (``mlp_triton._GRAD_X``, the ``fused`` weight gradients only).

The paper's heads (32 → 64 → 64 → 1 and → 3) on 2^19 and 2^22 rows of random features; forward
and backward timed apart (CUDA events around 20 repeats after 3 warm-up calls). The modules run
forward + backward with fp32 matmuls at full precision and in TF32, for reference.

    python -m benchmarks.field_heads_kernel --tag h200          # CUDA only
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path

import torch

from assets_store.atomic import atomic_write_text
from morpheus_core.geometry import mlp_triton
from morpheus_core.geometry.field_heads import head_parameters
from morpheus_core.geometry.nerf import NerfConfig, NerfField

RESULTS = Path(__file__).parent / "results"
FORWARD = [(64, 4), (128, 4), (128, 8), (256, 8)]
BACKWARD = [(32, 4), (64, 4), (64, 8), (128, 8)]
GEMM_BACKWARD = [(32, 4), (64, 4), (128, 4), (128, 8)]
PROGRAMS_PER_SM = [4, 8]
GRAD_X = ["store", "relaxed", "acq_rel"]


def cuda_ms(fn: Callable[[], object], repeats: int = 20, warmup: int = 3) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        fn()
        end.record()
        end.synchronize()
        times.append(start.elapsed_time(end))
    return statistics.median(times)


def cuda_ms_peak(fn: Callable[[], object]) -> tuple[float, float]:
    """``cuda_ms`` and the allocator's peak (GiB) above what was allocated before the calls."""
    torch.cuda.synchronize()
    base = torch.cuda.memory_allocated()
    torch.cuda.reset_peak_memory_stats()
    ms = cuda_ms(fn)
    return ms, (torch.cuda.max_memory_allocated() - base) / 2**30


def sweep(rows: int) -> list[dict[str, object]]:
    field = NerfField(NerfConfig(), generator=torch.Generator().manual_seed(0)).cuda()
    feats = torch.randn(rows, field.encoding.output_dim, device="cuda")
    density, albedo = head_parameters(field.density_mlp), head_parameters(field.albedo_mlp)
    grad_d, grad_a = torch.randn(rows, 1, device="cuda"), torch.randn(rows, 3, device="cuda")
    out: list[dict[str, object]] = []
    for tf32 in (False, True):
        torch.backends.cuda.matmul.allow_tf32 = tf32
        x = feats.clone().requires_grad_()

        def modules(x: torch.Tensor = x) -> None:
            field.zero_grad(set_to_none=True)
            torch.autograd.backward([field.density_mlp(x), field.albedo_mlp(x)], [grad_d, grad_a])

        out.append({"rows": rows, "path": f"modules, {'TF32' if tf32 else 'fp32'}", "fwd_bwd_ms": cuda_ms(modules)})
    torch.backends.cuda.matmul.allow_tf32 = False
    saved = (mlp_triton._FORWARD_BLOCK, mlp_triton._FORWARD_WARPS, mlp_triton._BACKWARD_BLOCK,
             mlp_triton._BACKWARD_WARPS, mlp_triton._PROGRAMS_PER_SM, mlp_triton._GRAD_X, mlp_triton._WEIGHT_GRADS)
    try:
        for block, warps in FORWARD:
            mlp_triton._FORWARD_BLOCK, mlp_triton._FORWARD_WARPS = block, warps
            ms = cuda_ms(lambda: mlp_triton.heads_forward(feats, density, albedo))
            out.append({"rows": rows, "path": "fused forward", "block": block, "warps": warps, "ms": ms})
        mlp_triton._WEIGHT_GRADS = "gemm"
        for block, warps in GEMM_BACKWARD:
            mlp_triton._BACKWARD_BLOCK, mlp_triton._BACKWARD_WARPS = block, warps
            ms, peak = cuda_ms_peak(lambda: mlp_triton.heads_backward(feats, density, albedo, grad_d, grad_a, True))
            out.append({"rows": rows, "path": "fused backward, gemm weight grads", "block": block, "warps": warps,
                        "ms": ms, "peak_gib": peak})
        mlp_triton._WEIGHT_GRADS = "fused"
        for grad_x, (block, warps), per_sm in itertools.product(GRAD_X, BACKWARD, PROGRAMS_PER_SM):
            (mlp_triton._GRAD_X, mlp_triton._BACKWARD_BLOCK, mlp_triton._BACKWARD_WARPS,
             mlp_triton._PROGRAMS_PER_SM) = grad_x, block, warps, per_sm
            ms, peak = cuda_ms_peak(lambda: mlp_triton.heads_backward(feats, density, albedo, grad_d, grad_a, True))
            out.append({"rows": rows, "path": f"fused backward, {grad_x}", "block": block, "warps": warps,
                        "programs_per_sm": per_sm, "ms": ms, "peak_gib": peak})
    finally:
        (mlp_triton._FORWARD_BLOCK, mlp_triton._FORWARD_WARPS, mlp_triton._BACKWARD_BLOCK,
         mlp_triton._BACKWARD_WARPS, mlp_triton._PROGRAMS_PER_SM, mlp_triton._GRAD_X, mlp_triton._WEIGHT_GRADS) = saved
    return out


def markdown(meta: dict[str, object], rows: list[dict[str, object]]) -> str:
    lines = [f"# Fused field heads: launch-size sweep — {meta['device']}, {meta['date']}", "",
             f"torch {meta['torch']}; command: `{meta['command']}`. Median of 20 CUDA-event timings after 3 "
             f"warm-up calls. The defaults: forward {meta['defaults']['forward']}, backward "
             f"{meta['defaults']['backward']}.", "",
             "| rows | path | rows per program | warps | backward programs per SM | ms | peak GiB above inputs |",
             "|---:|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        ms = r.get("ms", r.get("fwd_bwd_ms"))
        path = f"{r['path']} (fwd+bwd)" if "fwd_bwd_ms" in r else r["path"]
        lines.append(f"| 2^{int(r['rows']).bit_length() - 1} | {path} | "
                     f"{r.get('block', '–')} | {r.get('warps', '–')} | {r.get('programs_per_sm', '–')} | {ms:.2f} | "
                     + (f"{r['peak_gib']:.2f} |" if "peak_gib" in r else "– |"))
    for n in sorted({int(r["rows"]) for r in rows}):
        fused = [r for r in rows if r["rows"] == n and "ms" in r]
        best_f = min((r for r in fused if r["path"] == "fused forward"), key=lambda r: r["ms"])
        best_b = min((r for r in fused if r["path"].startswith("fused backward")), key=lambda r: r["ms"])
        mods = {r["path"]: r["fwd_bwd_ms"] for r in rows if r["rows"] == n and "fwd_bwd_ms" in r}
        lines.append("")
        lines.append(f"2^{n.bit_length() - 1} rows: best fused forward + backward {best_f['ms'] + best_b['ms']:.2f} ms "
                     f"(forward {best_f['block']}×{best_f['warps']}, "
                     f"{best_b['path']} {best_b['block']}×{best_b['warps']}, "
                     f"{best_b.get('programs_per_sm', '–')} per SM) against the modules ("
                     + ", ".join(f"{k}: {v:.2f} ms" for k, v in mods.items()) + ").")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tag", default="h200")
    ap.add_argument("--rows", type=int, nargs="+", default=[19, 22], help="log2 of the row counts")
    ap.add_argument("--results", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    if not torch.cuda.is_available():
        raise SystemExit("field_heads_kernel times CUDA kernels: no CUDA device here")
    rows = [r for n in args.rows for r in sweep(1 << n)]
    meta = {"date": datetime.now(timezone.utc).strftime("%Y-%m-%d"), "device": torch.cuda.get_device_name(),
            "torch": torch.__version__, "command": "python -m benchmarks.field_heads_kernel "
            + " ".join(argv if argv is not None else [f"--tag {args.tag}"]),
            "defaults": {"forward": f"{mlp_triton._FORWARD_BLOCK}×{mlp_triton._FORWARD_WARPS}",
                         "backward": f"{mlp_triton._BACKWARD_BLOCK}×{mlp_triton._BACKWARD_WARPS}, "
                                     f"{mlp_triton._WEIGHT_GRADS} weight grads ({mlp_triton._PROGRAMS_PER_SM} per "
                                     f"SM, {mlp_triton._GRAD_X} when fused)"}}
    stem = args.results / f"field_heads_{args.tag}"
    args.results.mkdir(parents=True, exist_ok=True)
    atomic_write_text(stem.with_suffix(".json"), json.dumps({"meta": meta, "rows": rows}, indent=2) + "\n")
    atomic_write_text(stem.with_suffix(".md"), markdown(meta, rows))
    print(markdown(meta, rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
