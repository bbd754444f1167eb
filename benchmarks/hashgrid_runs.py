"""The hash-grid backward's run reduction on one GPU: atomics per point against one per run of points in a cell.

``hashgrid_triton.RUN_REDUCTION`` picks the levels whose table gradient is summed over runs of
consecutive points in one cell before the atomics (``none``, ``dense``, ``all``). Which pays
depends on how the points come: uniform random points almost never share a cell with their
neighbour, while the NeRF stage's samples do (consecutive samples of the padded buffer are
neighbouring rays at one depth, a normal's six probes follow each other). Point sets, in the
paper grid's [0, 1]³ coordinates:

- ``uniform``: 2^20 uniform random points;
- ``rays``: a 128² view of 256 samples a ray through the [−1, 1]³ box, the samples inside a ball
  of radius 0.6 (the object an occupancy grid keeps), ordered as ``SampleBudget.gather`` orders
  them (every ray's first kept sample, then every ray's second, …);
- ``probes``: the ``rays`` samples within 0.05 of the ball's surface (where compositing weights
  are large), each followed by its six central-difference probes (``normal_eps`` 0.01), as the
  normals' density queries see them.

Timed: the Triton backward alone (table only, as the NeRF stage asks; and both gradients, as the
texture field asks), median of CUDA events, per mode; and each mode's max abs difference from
eager's table gradient.

    python -m benchmarks.hashgrid_runs    # on CUDA; writes benchmarks/results/hashgrid_runs_h200.{json,md}
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import sys
from pathlib import Path

import torch

from assets_store.atomic import atomic_write_text
from benchmarks.hashgrid_kernel import cuda_timed, make_grid
from morpheus_core.geometry import hashgrid_triton as kernels
from morpheus_core.geometry.hashgrid import eager_encode_backward

RESULTS = Path(__file__).resolve().parent / "results"
COMMAND = "python -m benchmarks.hashgrid_runs"
MODES = kernels.RUN_REDUCTIONS


def ray_samples(size: int = 128, n_samples: int = 256, radius: float = 0.6) -> torch.Tensor:
    """(N, 3) world points of one view's samples inside a ball, in ``SampleBudget``'s sample-major order."""
    dev = torch.device("cuda")
    u = (torch.arange(size, device=dev) + 0.5) / size * 2 - 1
    py, px = torch.meshgrid(u, u, indexing="ij")
    tan = math.tan(math.radians(20))
    origin = torch.tensor([0.3, 0.4, 2.5], device=dev)
    forward = -origin / origin.norm()
    right = torch.linalg.cross(forward, torch.tensor([0.0, 1.0, 0.0], device=dev))
    right = right / right.norm()
    up = torch.linalg.cross(right, forward)
    dirs = forward + tan * (px[..., None] * right - py[..., None] * up)
    dirs = (dirs / dirs.norm(dim=-1, keepdim=True)).reshape(-1, 3)
    t = 2.5 - math.sqrt(3) + (torch.arange(n_samples, device=dev) + 0.5) / n_samples * 2 * math.sqrt(3)
    points = origin + dirs[:, None, :] * t[None, :, None]  # (R, S, 3)
    keep = (points.norm(dim=-1) < radius) & (points.abs() <= 1).all(-1)
    return points.transpose(0, 1)[keep.t()]  # sample-major, as SampleBudget.gather


def point_sets() -> dict[str, torch.Tensor]:
    gen = torch.Generator(device="cuda").manual_seed(1)
    rays = ray_samples()
    shell = rays[(rays.norm(dim=-1) - 0.6).abs() < 0.05]
    offsets = torch.eye(3, device="cuda") * 0.01
    probes = torch.cat((shell[:, None] + offsets, shell[:, None] - offsets), 1).reshape(-1, 3)
    world = {"uniform": torch.rand(1 << 20, 3, device="cuda", generator=gen) * 2 - 1, "rays": rays, "probes": probes}
    return {name: ((x + 1) / 2).clamp(0, 1).contiguous() for name, x in world.items()}  # the field's [0, 1]³


def measure(iters: int, warmup: int) -> list[dict[str, object]]:
    grid = make_grid(0, table_std=0.1)
    tables, mask, table = grid.level_tables(), grid.level_mask, grid.table.detach()
    rows: list[dict[str, object]] = []
    default = kernels.RUN_REDUCTION
    for name, x in point_sets().items():
        grad_out = torch.randn(x.shape[0], grid.output_dim, device="cuda",
                               generator=torch.Generator(device="cuda").manual_seed(2))
        _, want = eager_encode_backward(x, table, tables, mask, grad_out, False, True)
        for mode in MODES:
            kernels.RUN_REDUCTION = mode
            _, got = kernels.encode_backward(x, table, tables, mask, grad_out, False, True)
            row: dict[str, object] = {
                "points": name, "n": int(x.shape[0]), "mode": mode,
                "table_only_ms": cuda_timed(lambda: kernels.encode_backward(
                    x, table, tables, mask, grad_out, False, True), iters, warmup)["median_ms"],  # noqa: B023
                "both_ms": cuda_timed(lambda: kernels.encode_backward(
                    x, table, tables, mask, grad_out, True, True), iters, warmup)["median_ms"],  # noqa: B023
                "max_abs_err": float((got - want).abs().max()), "max_abs_ref": float(want.abs().max()),
            }
            rows.append(row)
            print(row, flush=True)
    kernels.RUN_REDUCTION = default
    return rows


def markdown(meta: dict[str, object], rows: list[dict[str, object]]) -> str:
    lines = ["# Hash-grid backward: atomics per point or per run of points in one cell", "",
             f"{meta['date']} · {meta['device']} · torch {meta['torch']} · triton {meta['triton']}", "",
             f"Command: `{meta['command']}`. Paper grid (16 levels × 2 features, 2^19 table: levels 0–4 dense). "
             f"Triton backward alone, median of {meta['iters']} CUDA-event timings; speed-up against `none` "
             "(one atomic per point and corner, the kernel before). Point sets: the module docstring.", "",
             "| points | N | mode | table only (ms) | speed-up | both grads (ms) | speed-up | max abs err vs eager |",
             "|---|---:|---|---:|---:|---:|---:|---:|"]
    base = {(r["points"], "t"): float(r["table_only_ms"]) for r in rows if r["mode"] == "none"}  # type: ignore[arg-type]
    base |= {(r["points"], "b"): float(r["both_ms"]) for r in rows if r["mode"] == "none"}  # type: ignore[arg-type]
    for r in rows:
        t, b = float(r["table_only_ms"]), float(r["both_ms"])  # type: ignore[arg-type]
        lines.append(f"| {r['points']} | {r['n']} | {r['mode']} | {t:.3f} | {base[(r['points'], 't')] / t:.2f}× | "
                     f"{b:.3f} | {base[(r['points'], 'b')] / b:.2f}× | {float(r['max_abs_err']):.2g} |")  # type: ignore[arg-type]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--iters", type=int, default=30)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--tag", default="h200")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    if not torch.cuda.is_available():
        sys.exit("benchmarks.hashgrid_runs times CUDA kernels and needs a CUDA device; none is available here")
    import triton

    rows = measure(args.iters, args.warmup)
    meta = {"date": dt.datetime.now().isoformat(timespec="seconds"), "device": torch.cuda.get_device_name(),
            "torch": torch.__version__, "triton": triton.__version__, "command": COMMAND, "iters": args.iters}
    stem = args.out / f"hashgrid_runs_{args.tag}"
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(stem.with_suffix(".json"), json.dumps({"meta": meta, "rows": rows}, indent=2) + "\n")
    atomic_write_text(stem.with_suffix(".md"), markdown(meta, rows))
    print(f"wrote {stem}.json and .md", flush=True)


if __name__ == "__main__":
    main()
