"""Rasteriser speed: 512² renders of ~100k- and ~300k-face icospheres, batch 1 and 4, forward and
forward+backward through the anti-aliased mask and an interpolated per-vertex colour loss.

    python benchmarks/raster_speed.py                 # CPU, writes benchmarks/results/raster_speed_cpu.*
    python benchmarks/raster_speed.py --device cuda   # GPU, tag from the device name (e.g. h200)
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import statistics
import time
from datetime import datetime, timezone
from pathlib import Path

import torch
import trimesh

from assets_store.atomic import atomic_write_text
from benchmarks.timing import sync_device
from morpheus_core.cameras import OrbitConfig, sample_orbit
from morpheus_core.render.antialias import antialias, silhouette_crossings
from morpheus_core.render.raster import RasterConfig, interpolate, rasterize

# Icosphere subdivisions: 20·4^s faces — 6 → 81,920 (the "~100k" case), 7 → 327,680 ("~300k").
SUBDIVISIONS = {"100k": 6, "300k": 7}


def _scene(subdivisions: int, batch: int, device: torch.device):
    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.8)
    vertices = torch.tensor(ico.vertices, dtype=torch.float32, device=device)
    faces = torch.tensor(ico.faces, dtype=torch.int64, device=device)
    cams = sample_orbit(batch, OrbitConfig(), torch.Generator().manual_seed(batch)).to(device)
    g = torch.Generator().manual_seed(0)
    colours = torch.rand(vertices.shape[0], 3, generator=g).to(device)
    return vertices, faces, cams.world_to_clip(), colours


def _step(vertices, faces, w2c, colours, size: int, config: RasterConfig, target: torch.Tensor | None):
    """One render; with ``target`` also the loss and its backward to vertices and colours."""
    homog = torch.cat([vertices, torch.ones_like(vertices[:, :1])], -1)
    clip = torch.einsum("bij,vj->bvi", w2c, homog)
    frags = rasterize(clip, faces, size, size, config)
    crossings = silhouette_crossings(frags)
    image = antialias(torch.cat([interpolate(colours, frags), frags.mask], -1), frags, crossings)
    if target is not None:
        loss = ((image - target) ** 2).mean()
        loss.backward()
    return frags, crossings


def _time(fn, device: torch.device, repeats: int) -> list[float]:
    fn()  # warm-up (allocator, lazy initialisation)
    times = []
    for _ in range(repeats):
        sync_device(device)
        t0 = time.perf_counter()
        fn()
        sync_device(device)
        times.append((time.perf_counter() - t0) * 1e3)
    return times


def measure(device: torch.device, size: int, batches: list[int], meshes: list[str], repeats: int,
            config: RasterConfig) -> list[dict]:
    rows = []
    for name in meshes:
        for batch in batches:
            vertices, faces, w2c, colours = _scene(SUBDIVISIONS[name], batch, device)
            target = torch.full((batch, size, size, 4), 0.5, device=device)
            leaf_v = vertices.clone().requires_grad_(True)
            leaf_c = colours.clone().requires_grad_(True)

            def forward(v=vertices, f=faces, m=w2c, c=colours):
                with torch.no_grad():
                    return _step(v, f, m, c, size, config, None)

            def forward_backward(v=leaf_v, f=faces, m=w2c, c=leaf_c, t=target):
                v.grad = c.grad = None
                return _step(v, f, m, c, size, config, t)

            frags, crossings = forward()
            if device.type == "cuda":
                torch.cuda.reset_peak_memory_stats(device)
            fwd = _time(forward, device, repeats)
            fwd_bwd = _time(forward_backward, device, repeats)
            assert leaf_v.grad is not None and torch.isfinite(leaf_v.grad).all()
            row = {
                "mesh": name, "faces": int(faces.shape[0]), "batch": batch, "size": size,
                "covered_pixels": int(frags.pixel_index.numel()), "silhouette_pairs": int(crossings.t.numel()),
                "forward_ms": round(statistics.median(fwd), 2),
                "forward_backward_ms": round(statistics.median(fwd_bwd), 2),
                "forward_min_ms": round(min(fwd), 2), "forward_backward_min_ms": round(min(fwd_bwd), 2),
                "repeats": repeats,
            }
            if device.type == "cuda":
                row["peak_memory_mib"] = round(torch.cuda.max_memory_allocated(device) / 2**20, 1)
            print(row, flush=True)
            rows.append(row)
    return rows


def _device_tag(device: torch.device) -> tuple[str, str]:
    if device.type != "cuda":
        return "cpu", platform.processor() or platform.machine() or "cpu"
    name = torch.cuda.get_device_name(device)
    return re.sub(r"[^a-z0-9]+", "", name.split()[-1].lower()) or "cuda", name


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 4])
    parser.add_argument("--meshes", nargs="+", default=list(SUBDIVISIONS), choices=list(SUBDIVISIONS))
    parser.add_argument("--repeats", type=int, default=None, help="timed repeats (default 3 on CPU, 10 on CUDA)")
    parser.add_argument("--max-pairs", type=int, default=RasterConfig().max_pairs_per_chunk)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results"))
    parser.add_argument("--tag", default=None, help="result file suffix (default: cpu, or the GPU model)")
    args = parser.parse_args()
    device = torch.device(args.device)
    repeats = args.repeats or (10 if device.type == "cuda" else 3)
    config = RasterConfig(max_pairs_per_chunk=args.max_pairs)
    rows = measure(device, args.size, args.batches, args.meshes, repeats, config)
    tag, machine = _device_tag(device)
    tag = args.tag or tag
    summary = {"date": datetime.now(timezone.utc).strftime("%Y-%m-%d"), "device": machine,
               "torch": torch.__version__, "cpu_threads": torch.get_num_threads(),
               "max_pairs_per_chunk": args.max_pairs, "load_average_1min": round(os.getloadavg()[0], 2),
               "rows": rows}
    atomic_write_text(args.out / f"raster_speed_{tag}.json", json.dumps(summary, indent=2))
    mem_col = device.type == "cuda"
    lines = [f"# Rasteriser at {args.size}², icosphere r = 0.8 from random orbit views", "",
             f"Device: {machine}; torch {torch.__version__}; {torch.get_num_threads()} CPU threads; "
             f"date {summary['date']}; median of {repeats} repeats after one warm-up; "
             f"chunk {args.max_pairs} pairs; 1-min load average {summary['load_average_1min']} at the end "
             "(other jobs share this machine: compare the minima when it is high).", "",
             "Forward = visibility + barycentrics + silhouette crossings + anti-aliased colour and mask. "
             "Forward+backward adds an MSE loss on both and its backward to vertices and vertex colours.", "",
             "| faces | batch | covered px | silhouette pairs | forward median / min (ms) "
             "| forward+backward median / min (ms) |"
             + (" peak mem (MiB) |" if mem_col else ""),
             "|---:|---:|---:|---:|---:|---:|" + ("---:|" if mem_col else "")]
    lines += [f"| {r['faces']:,} | {r['batch']} | {r['covered_pixels']:,} | {r['silhouette_pairs']:,} | "
              f"{r['forward_ms']:.0f} / {r['forward_min_ms']:.0f} | "
              f"{r['forward_backward_ms']:.0f} / {r['forward_backward_min_ms']:.0f} |"
              + (f" {r['peak_memory_mib']:.0f} |" if mem_col else "") for r in rows]
    atomic_write_text(args.out / f"raster_speed_{tag}.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
