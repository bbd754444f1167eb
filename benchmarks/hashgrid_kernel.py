"""Hash-grid encode kernels on one GPU: eager PyTorch, torch.compile, and the fused Triton kernels.

The paper's NeRF grid (``HashGridConfig()``: 16 levels × 2 features, 2^19-row tables) encoding
2^16, 2^18 and 2^20 points; per kernel path, the forward alone and forward + backward with both
gradients (table and points), timed with CUDA events over 20 iterations after warm-up; and the
Triton kernels' max abs error against eager (forward, grad_table, grad_x) at 2^16 points.

Paths (applied as execution settings, ``morpheus_core.runtime.execution``, as a pipeline run does):
- eager: ``execution.hashgrid=eager execution.compile=false``, the tensor code uncompiled;
- compiled: ``execution.hashgrid=eager`` with ``compiled_for``'s default on CUDA (``torch.compile``,
  dynamic shapes): the CUDA default before the Triton kernels;
- triton: ``execution.hashgrid=triton``, the fused kernels (``hashgrid_triton``): the CUDA default now.

    python -m benchmarks.hashgrid_kernel    # on CUDA; writes benchmarks/results/hashgrid_kernel_h200.{json,md}
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import platform
import statistics
import sys
from collections.abc import Callable
from pathlib import Path

import torch

from assets_store.atomic import atomic_write_text
from morpheus_core.geometry.hashgrid import HashGrid, HashGridConfig
from morpheus_core.runtime.devices import compile_enabled
from morpheus_core.runtime.execution import ExecutionConfig, apply_execution

RESULTS = Path(__file__).resolve().parent / "results"
COMMAND = "python -m benchmarks.hashgrid_kernel"
SIZES = (1 << 16, 1 << 18, 1 << 20)
PATHS: dict[str, ExecutionConfig] = {
    "eager": ExecutionConfig(hashgrid="eager", compile=False),
    "compiled": ExecutionConfig(hashgrid="eager", compile=True),
    "triton": ExecutionConfig(hashgrid="triton", compile=True),
}


def use_path(name: str) -> None:
    apply_execution(PATHS[name])


def cuda_timed(fn: Callable[[], object], iters: int, warmup: int) -> dict[str, float]:
    """Median / mean / min of per-iteration CUDA-event times (ms), and the peak memory of the timed loop."""
    for _ in range(warmup):
        fn()
    torch.cuda.synchronize()
    torch.cuda.reset_peak_memory_stats()
    events = [(torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)) for _ in range(iters)]
    for start, end in events:
        start.record()
        fn()
        end.record()
    torch.cuda.synchronize()
    times = [start.elapsed_time(end) for start, end in events]
    return {"median_ms": statistics.median(times), "mean_ms": statistics.fmean(times), "min_ms": min(times),
            "peak_gib": torch.cuda.max_memory_allocated() / 2**30}


def make_grid(seed: int, table_std: float | None = None) -> HashGrid:
    grid = HashGrid(HashGridConfig(), generator=torch.Generator().manual_seed(seed)).cuda()
    if table_std is not None:  # the default init (±1e-4) would make every error look tiny
        with torch.no_grad():
            grid.table.normal_(0, table_std, generator=torch.Generator(device="cuda").manual_seed(seed))
    return grid


def bench(path: str, n: int, iters: int, warmup: int) -> dict[str, float]:
    use_path(path)
    grid = make_grid(0)
    x = torch.rand(n, 3, device="cuda", generator=torch.Generator(device="cuda").manual_seed(1))
    grad_out = torch.randn(n, grid.output_dim, device="cuda", generator=torch.Generator(device="cuda").manual_seed(2))
    xi = x.clone().requires_grad_(True)

    def forward() -> None:
        with torch.no_grad():
            grid(x)

    def forward_backward() -> None:
        grid.table.grad = None
        xi.grad = None
        grid(xi).backward(grad_out)

    fwd = cuda_timed(forward, iters, warmup)
    both = cuda_timed(forward_backward, iters, warmup)
    assert xi.grad is not None and grid.table.grad is not None
    return {"forward_median_ms": fwd["median_ms"], **both}


def bench_kernels(n: int, iters: int, warmup: int) -> dict[str, float]:
    """The Triton kernels alone (direct calls: no autograd, no dispatch), medians in ms."""
    from morpheus_core.geometry import hashgrid_triton as kernels

    grid = make_grid(0)
    tables, mask, table = grid.level_tables(), grid.level_mask, grid.table.detach()
    x = torch.rand(n, 3, device="cuda", generator=torch.Generator(device="cuda").manual_seed(1))
    grad_out = torch.randn(n, grid.output_dim, device="cuda", generator=torch.Generator(device="cuda").manual_seed(2))
    calls = {
        "forward": lambda: kernels.encode_forward(x, table, tables, mask),
        "backward_both": lambda: kernels.encode_backward(x, table, tables, mask, grad_out, True, True),
        "backward_table": lambda: kernels.encode_backward(x, table, tables, mask, grad_out, False, True),
        "backward_x": lambda: kernels.encode_backward(x, table, tables, mask, grad_out, True, False),
    }
    return {f"{name}_ms": cuda_timed(fn, iters, warmup)["median_ms"] for name, fn in calls.items()}


def errors(n: int) -> dict[str, dict[str, float]]:
    """Max abs difference of each path's forward, grad_table and grad_x from eager's (table ~ N(0, 0.1))."""
    grid = make_grid(3, table_std=0.1)
    x = torch.rand(n, 3, device="cuda", generator=torch.Generator(device="cuda").manual_seed(4))
    grad_out = torch.randn(n, grid.output_dim, device="cuda", generator=torch.Generator(device="cuda").manual_seed(5))

    def run(path: str) -> dict[str, torch.Tensor]:
        use_path(path)
        xi = x.clone().requires_grad_(True)
        grid.table.grad = None
        out = grid(xi)
        out.backward(grad_out)
        return {"forward": out.detach(), "grad_table": grid.table.grad.clone(), "grad_x": xi.grad.clone()}

    ref = run("eager")
    result: dict[str, dict[str, float]] = {}
    for path in ("triton", "compiled"):
        got = run(path)
        for key, want in ref.items():
            result.setdefault(key, {"max_abs_ref": float(want.abs().max())})
            result[key][f"{path}_max_abs_err"] = float((got[key] - want).abs().max())
    return result


def markdown(meta: dict[str, object], rows: list[dict[str, object]], kernel_rows: list[dict[str, object]],
             errs: dict[str, object]) -> str:
    lines = [
        "# Hash-grid encode kernels (paper grid: 16 levels × 2 features, 2^19 table)", "",
        f"{meta['date']} · {meta['device']} · torch {meta['torch']} · triton {meta['triton']}", "",
        f"Command: `{meta['command']}`", "",
        f"Per point count: forward alone (no grad) and forward + backward with both gradients (table and "
        f"points); CUDA events, median of {meta['iters']} iterations after {meta['warmup']} warm-up. "
        "eager = the tensor code uncompiled; compiled = it under torch.compile (the CUDA default before); "
        "triton = the fused kernels (the CUDA default now).", "",
        "| points | path | fwd ms | fwd+bwd ms (median) | fwd+bwd min | peak GiB | fwd+bwd speed-up vs eager "
        "| vs compiled |",
        "|---:|---|---:|---:|---:|---:|---:|---:|",
    ]
    base: dict[tuple[object, str], float] = {}
    for row in rows:
        if "median_ms" in row:
            base[(row["points"], str(row["path"]))] = float(row["median_ms"])  # type: ignore[arg-type]
    for row in rows:
        n = row["points"]
        label = f"2^{int(n).bit_length() - 1}"  # type: ignore[call-overload]
        if "error" in row:
            lines.append(f"| {label} | {row['path']} | – | – | – | – | – | {row['error']} |")
            continue
        med = float(row["median_ms"])  # type: ignore[arg-type]

        def ratio(other: str, n: object = n, med: float = med) -> str:
            ref = base.get((n, other))
            return f"{ref / med:.1f}×" if ref else "–"

        lines.append(f"| {label} | {row['path']} | {row['forward_median_ms']:.3f} | {med:.3f} | "
                     f"{row['min_ms']:.3f} | {row['peak_gib']:.2f} | {ratio('eager')} | {ratio('compiled')} |")
    lines += ["", "The Triton kernels alone (direct calls, no autograd or dispatch; median ms). Where the "
              "end-to-end step takes longer than forward + backward here, the step is bound by the CPU "
              "(Python, autograd and kernel launches).", "",
              "| points | forward | backward, both grads | backward, table only | backward, x only |",
              "|---:|---:|---:|---:|---:|"]
    for row in kernel_rows:
        label = f"2^{int(row['points']).bit_length() - 1}"  # type: ignore[call-overload]
        if "error" in row:
            lines.append(f"| {label} | {row['error']} | | | |")
            continue
        lines.append(f"| {label} | {row['forward_ms']:.3f} | {row['backward_both_ms']:.3f} | "
                     f"{row['backward_table_ms']:.3f} | {row['backward_x_ms']:.3f} |")
    lines += ["", f"Max abs error against eager at {meta['error_points']} points (table ~ N(0, 0.1)):", ""]
    if "error" in errs:
        lines.append(f"failed: {errs['error']}")
    else:
        lines += ["| quantity | max abs (eager) | triton max abs err | compiled max abs err |", "|---|---:|---:|---:|"]
        for key, vals in errs.items():
            v = dict(vals)  # type: ignore[call-overload]
            lines.append(f"| {key} | {v['max_abs_ref']:.3g} | {v.get('triton_max_abs_err', float('nan')):.3g} | "
                         f"{v.get('compiled_max_abs_err', float('nan')):.3g} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--iters", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--tag", default="h200", help="results file suffix")
    args = parser.parse_args()
    if not torch.cuda.is_available():
        sys.exit("benchmarks.hashgrid_kernel times CUDA kernels and needs a CUDA device; none is available here")
    device = torch.device("cuda")
    import triton

    # Whether compiled_for compiled on CUDA before this run applied its paths (the default: yes).
    compiled_default = compile_enabled(device)
    rows: list[dict[str, object]] = []
    for n in SIZES:
        for path in PATHS:
            try:
                row: dict[str, object] = dict(bench(path, n, args.iters, args.warmup))
            except Exception as exc:  # one failing path must not hide the others
                row = {"error": f"{type(exc).__name__}: {exc}"[:300]}
            rows.append({"points": n, "path": path, **row})
            print(rows[-1], flush=True)
    kernel_rows: list[dict[str, object]] = []
    for n in SIZES:
        try:
            krow: dict[str, object] = dict(bench_kernels(n, args.iters, args.warmup))
        except Exception as exc:
            krow = {"error": f"{type(exc).__name__}: {exc}"[:300]}
        kernel_rows.append({"points": n, **krow})
        print(kernel_rows[-1], flush=True)
    error_points = SIZES[0]
    try:
        errs: dict[str, object] = dict(errors(error_points))
    except Exception as exc:
        errs = {"error": f"{type(exc).__name__}: {exc}"[:300]}
    print(errs, flush=True)
    meta = {
        "date": dt.datetime.now().isoformat(timespec="seconds"),
        "device": torch.cuda.get_device_name(device),
        "torch": torch.__version__,
        "triton": triton.__version__,
        "python": platform.python_version(),
        "command": COMMAND,
        "iters": args.iters,
        "warmup": args.warmup,
        "error_points": error_points,
        "compile_was_enabled": compiled_default,
        "config": "HashGridConfig() defaults: 16 levels, 2 features, log2 table 19, base 16, scale 1.447",
    }
    stem = RESULTS / f"hashgrid_kernel_{args.tag}"
    atomic_write_text(stem.with_suffix(".json"), json.dumps({"meta": meta, "rows": rows, "kernels": kernel_rows,
                                                                   "errors": errs}, indent=2)
                      + "\n")
    atomic_write_text(stem.with_suffix(".md"), markdown(meta, rows, kernel_rows, errs))
    print(f"wrote {stem}.json and .md", flush=True)


if __name__ == "__main__":
    main()
