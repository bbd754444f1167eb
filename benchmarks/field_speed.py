"""Speed of the NeRF side of the render stack: hash-grid encode and volume rendering.

Measures (forward + backward, median of repeats):
- the paper's hash grid (16 levels × 2 features, table 2^19) encoding 2^18 points, eager and,
  on CUDA, under ``torch.compile``;
- a volume render of a 128² image at 256 samples per ray of the paper-size NeRF (blob init),
  with and without the occupancy grid and the central-difference normals;
- the field's two MLP heads (32 → 64 → 64 → 1 and → 3) on 2^22 rows, forward + backward, as
  ``nn.Sequential`` modules and, on CUDA, as the fused kernels (``execution.field_mlp``), with fp32
  matmuls full precision and TF32; and the volume render with either.

    python benchmarks/field_speed.py --tag cpu            # writes benchmarks/results/field_speed_cpu.{json,md}
    python benchmarks/field_speed.py --tag h200 --device cuda
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import datetime as dt
import json
import platform
import statistics
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import torch

from benchmarks.timing import sync_device
from morpheus_core.cameras import sample_orbit
from morpheus_core.geometry.field_heads import evaluate_heads
from morpheus_core.geometry.hashgrid import HashGrid, HashGridConfig
from morpheus_core.geometry.nerf import NerfConfig, NerfField
from morpheus_core.render.volume import OccupancyGrid, OccupancyGridConfig, VolumeRenderConfig, render_volume
from morpheus_core.runtime.execution import current_execution, executing

RESULTS = Path(__file__).resolve().parent / "results"


def timed(fn: Callable[[], None], device: torch.device, repeats: int, warmup: int) -> dict[str, float]:
    for _ in range(warmup):
        fn()
    sync_device(device)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        sync_device(device)
        times.append((time.perf_counter() - start) * 1000)
    row = {"median_ms": statistics.median(times), "min_ms": min(times), "repeats": repeats}
    if device.type == "cuda":
        row["peak_gib"] = torch.cuda.max_memory_allocated(device) / 2**30
    return row


def bench_hashgrid(device: torch.device, repeats: int, compiled: bool) -> dict[str, float]:
    grid = HashGrid(HashGridConfig(), generator=torch.Generator().manual_seed(0)).to(device)
    x = torch.rand(1 << 18, 3, generator=torch.Generator().manual_seed(1)).to(device)
    encode = torch.compile(grid) if compiled else grid

    def step() -> None:
        grid.table.grad = None
        encode(x).square().sum().backward()

    return timed(step, device, repeats, warmup=3 if compiled else 1)


@contextlib.contextmanager
def settings(heads: str, tf32: bool) -> Iterator[None]:
    """``execution.field_mlp`` and PyTorch's TF32 switch for fp32 matmuls, restored afterwards."""
    old_tf32 = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = tf32
    try:
        with executing(dataclasses.replace(current_execution(), field_mlp=heads)):  # type: ignore[arg-type]
            yield
    finally:
        torch.backends.cuda.matmul.allow_tf32 = old_tf32


def bench_heads(device: torch.device, repeats: int, rows: int, heads: str, tf32: bool) -> dict[str, float]:
    field = NerfField(NerfConfig(), generator=torch.Generator().manual_seed(6)).to(device)
    feats = torch.randn(rows, field.encoding.output_dim, generator=torch.Generator().manual_seed(7)).to(device)
    feats.requires_grad_()

    def step() -> None:
        field.zero_grad(set_to_none=True)
        feats.grad = None
        density, albedo = evaluate_heads(feats, field.density_mlp, field.albedo_mlp)
        (density.square().mean() + albedo.square().mean()).backward()

    with settings(heads, tf32):
        return timed(step, device, repeats, warmup=2)


def bench_volume(
    device: torch.device, repeats: int, occupancy: bool, normals: bool, size: int = 128, samples: int = 256
) -> dict[str, float]:
    field = NerfField(NerfConfig(), generator=torch.Generator().manual_seed(2)).to(device)
    cams = sample_orbit(1, generator=torch.Generator().manual_seed(3)).to(device)
    config = VolumeRenderConfig(n_samples=samples, with_normals=normals)
    grid = None
    if occupancy:
        grid = OccupancyGrid(OccupancyGridConfig(), field.bbox_radius).to(device)
        grid.refresh(field, torch.Generator().manual_seed(4))
    gen = torch.Generator().manual_seed(5)

    def step() -> None:
        field.zero_grad(set_to_none=True)
        out = render_volume(field, cams, size, size, config, occupancy=grid, generator=gen)
        (out.rgb.mean() + out.opacity.mean()).backward()

    row = timed(step, device, repeats, warmup=2)
    if grid is not None:
        row["occupied_fraction"] = grid.occupied_fraction
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--tag", default=None, help="results file suffix (default: the device type)")
    parser.add_argument("--repeats", type=int, default=None)
    args = parser.parse_args()
    device = torch.device(args.device)
    cuda = device.type == "cuda"
    repeats = args.repeats or (20 if cuda else 3)
    rows: list[dict[str, object]] = []

    def record(name: str, fn: Callable[[], dict[str, float]]) -> None:
        try:
            result: dict[str, object] = dict(fn())
        except Exception as exc:  # one failing configuration must not hide the others
            result = {"error": f"{type(exc).__name__}: {exc}"[:300]}
        rows.append({"benchmark": name, **result})
        print(name, result, flush=True)

    record("hashgrid 2^18 pts fwd+bwd (eager)", lambda: bench_hashgrid(device, repeats, compiled=False))
    if cuda:
        record("hashgrid 2^18 pts fwd+bwd (torch.compile)", lambda: bench_hashgrid(device, repeats, compiled=True))
    vol_repeats = repeats if cuda else 1
    # Normals cost six extra density queries per sample (central differences).
    for occupancy, normals in ((True, True), (True, False), (False, False)):
        name = "volume 128² × 256 spp fwd+bwd, " + ("occupancy grid" if occupancy else "no skipping")
        name += ", normals" if normals else ", no normals"
        record(name, lambda o=occupancy, n=normals: bench_volume(device, vol_repeats, occupancy=o, normals=n))
    # The fused kernels' products are TF32 whatever the switch says: one row for them.
    choices = [("eager", False), ("eager", True)] + ([("triton", True)] if cuda else [])
    head_rows = 1 << (22 if cuda else 16)
    for heads, tf32 in choices:
        precision = "TF32" if tf32 else "fp32"
        label = "fused kernels, TF32 products" if heads == "triton" else f"modules, {precision} matmuls"
        record(f"field heads 2^{head_rows.bit_length() - 1} rows fwd+bwd ({label})",
               lambda h=heads, t=tf32: bench_heads(device, repeats, head_rows, h, t))
        if cuda:
            def volume(h: str = heads, t: bool = tf32) -> dict[str, float]:
                with settings(h, t):
                    return bench_volume(device, vol_repeats, occupancy=True, normals=False)

            record(f"volume 128² × 256 spp fwd+bwd, occupancy grid, no normals ({label})", volume)

    meta = {
        "date": dt.datetime.now().isoformat(timespec="seconds"),
        "device": torch.cuda.get_device_name(device) if cuda else f"CPU ({platform.processor() or platform.machine()})",
        "threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "python": platform.python_version(),
    }
    tag = args.tag or device.type
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"field_speed_{tag}.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=2) + "\n")
    lines = [
        f"# Field speed ({tag})", "",
        f"{meta['date']} · {meta['device']} · torch {meta['torch']} · {meta['threads']} threads", "",
        f"Command: `python benchmarks/field_speed.py --device {args.device} --tag {tag}`", "",
        "| benchmark | median ms | min ms | peak GiB | note |", "|---|---|---|---|---|",
    ]
    for row in rows:
        if "error" in row:
            lines.append(f"| {row['benchmark']} | – | – | – | {row['error']} |")
            continue
        peak = f"{row['peak_gib']:.2f}" if "peak_gib" in row else "–"
        note = f"occupied {row['occupied_fraction']:.1%} of cells" if "occupied_fraction" in row else ""
        lines.append(f"| {row['benchmark']} | {row['median_ms']:.1f} | {row['min_ms']:.1f} | {peak} | {note} |")
    (RESULTS / f"field_speed_{tag}.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
