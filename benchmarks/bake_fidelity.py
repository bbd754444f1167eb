"""How much texture detail the UV bake keeps: the exported GLB against the colour field it was baked from.

At the paper preset the GLB scored 0.8–3 dB below the texture stage's own output (mesh + field) on the
mug, box and chair in ``early_stop_paper10_h200.md`` (bottle, whose colours are smooth, lost nothing),
with the same Chamfer distance and a lower high-frequency ratio. The bench-cpu size loses nothing
(256² maps of a small field). This isolates the two steps that could lose detail between the field and the GLB:
the decimation to the export face budget (vertex clustering) and the bake into a square texture.

A wobbly icosphere (``--subdivisions``) is coloured by a paper-sized texture field whose hash-grid table
is scaled up from its ~1e-4 initialisation (``--detail``), so that every level carries detail, as a
trained field's fine levels do. For each (face budget, texture size) the mesh is baked, exported as
GLB, read back and rendered. The renders are compared with the field rendered on the source mesh from
the same four views: PSNR and ``hf_ratio`` (high-frequency energy against the field's render).

    python -m benchmarks.bake_fidelity          # CPU, ~3 min; writes benchmarks/results/bake_fidelity_cpu.{json,md}
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import torch
import trimesh

from benchmarks.quality import machine, write_results
from morpheus_core.cameras import orbit
from morpheus_core.export.gltf import export_glb
from morpheus_core.export.uv_bake import BakeConfig, bake_uv
from morpheus_core.geometry.mesh import Mesh
from morpheus_core.metrics.image import hf_ratio, psnr
from morpheus_core.render.mesh_renderer import render_mesh
from morpheus_core.render.textured import load_textured, render_textured
from morpheus_core.texture import TextureField, TextureFieldConfig

RESULTS = Path(__file__).resolve().parent / "results"
NO_BUDGET = 10**9


def wobbly_sphere(subdivisions: int) -> Mesh:
    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.6)
    v = torch.tensor(ico.vertices, dtype=torch.float32)
    v = v * (1 + 0.08 * torch.sin(5 * v[:, :1]) * torch.cos(4 * v[:, 1:2]))  # curvature varies over the surface
    return Mesh(v, torch.tensor(ico.faces, dtype=torch.int64))


def detailed_field(detail: float, seed: int = 1) -> TextureField:
    field = TextureField(TextureFieldConfig(), generator=torch.Generator().manual_seed(seed))
    with torch.no_grad():
        field.encoding.table.mul_(detail)
    return field


def run(subdivisions: int, detail: float, sizes: list[int], budgets: list[int],
        resolution: int) -> list[dict[str, Any]]:
    mesh, field = wobbly_sphere(subdivisions), detailed_field(detail)
    cams = orbit([15.0, 15.0, 15.0, -10.0], [0.0, 90.0, 200.0, 300.0], distance=2.2)
    with torch.no_grad():
        truth = render_mesh(mesh, cams, resolution, resolution, field).rgb_chw()
    rows = []
    for budget in budgets:
        for size in sizes:
            start = time.perf_counter()
            with torch.no_grad():
                baked = bake_uv(mesh, field, BakeConfig(texture_size=size, max_faces=budget))
            with tempfile.TemporaryDirectory() as tmp:
                export_glb(baked, Path(tmp) / "asset.glb")
                asset = load_textured(Path(tmp) / "asset.glb")
            with torch.no_grad():
                got = render_textured(asset, cams, resolution, resolution).rgb_chw()
            n = len(cams)
            rows.append({
                "faces": int(baked.faces.shape[0]), "source_faces": mesh.num_faces,
                "budget": None if budget == NO_BUDGET else budget, "texture_size": size,
                "coverage": round(baked.coverage, 4),
                "psnr": sum(psnr(got[i], truth[i]) for i in range(n)) / n,
                "hf_ratio": sum(hf_ratio(got[i:i + 1], truth[i:i + 1]) or 0.0 for i in range(n)) / n,
                "seconds": round(time.perf_counter() - start, 1),
            })
            print(rows[-1], flush=True)
    return rows


def markdown(rows: list[dict[str, Any]]) -> str:
    lines = ["| faces (source → exported) | texture | UV coverage | PSNR vs field (dB) | hf ratio | s |",
             "|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['source_faces']} → {r['faces']} | {r['texture_size']}² | {r['coverage']:.3f} | "
                     f"{r['psnr']:.2f} | {r['hf_ratio']:.3f} | {r['seconds']:.0f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subdivisions", type=int, default=6, help="icosphere subdivisions (6: 81,920 faces)")
    ap.add_argument("--detail", type=float, default=30000.0, help="scale of the field's hash-grid table")
    ap.add_argument("--sizes", type=int, nargs="+", default=[1024, 2048])
    ap.add_argument("--budgets", type=int, nargs="+", default=[NO_BUDGET, 50_000],
                    help="export face budgets (the default 50,000 decimates the 81,920-face sphere)")
    ap.add_argument("--resolution", type=int, default=256, help="render size (px), as the quality benchmark")
    ap.add_argument("--results", type=Path, default=RESULTS)
    ap.add_argument("--name", default="bake_fidelity_cpu")
    args = ap.parse_args(argv)
    start = time.perf_counter()
    rows = run(args.subdivisions, args.detail, args.sizes, args.budgets, args.resolution)
    about = ("A paper-sized texture field with detail at every hash-grid level, on a wobbly icosphere, baked "
             "and exported as GLB, then rendered and compared with the field rendered on the source mesh "
             "(4 views). Decimation to the export budget (vertex clustering) and the texture size are varied "
             "one at a time. See the module docstring of `benchmarks/bake_fidelity.py`.")
    payload = {"title": "UV bake fidelity: GLB against its colour field", "machine": machine("cpu"),
               "date": datetime.now(timezone.utc).strftime("%Y-%m-%d"),
               "command": "python -m benchmarks.bake_fidelity " + " ".join(sys.argv[1:] if argv is None else argv),
               "wall_s": time.perf_counter() - start, "about": about, "rows": rows, "args": {
                   k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}}
    write_results(args.results, args.name, payload, markdown(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
