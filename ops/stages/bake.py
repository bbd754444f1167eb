"""Final stage: UV-unwrap the mesh, bake the texture field, export GLB (+ OBJ) and previews.

Before unwrapping, components smaller than ``min_component_share`` of the surface area are dropped
(DMTet leaves floaters: specks of the NeRF's fuzz that xatlas would waste charts on and viewers
would show), and the cleaned mesh's topology goes into the manifest so QA and people can see what
was decided.

The exported GLB is read back and rendered (not the field it came from), so the reference-view
PSNR and the turntable show what a user will load. Output: ``asset.glb``, ``asset.obj`` (+ .mtl,
.png), ``turntable.png`` (8 views around the object), ``reference_view.png`` (photo | asset).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from morpheus_core.cameras import turntable
from morpheus_core.export.gltf import export_glb, export_obj
from morpheus_core.export.uv_bake import BakeConfig, bake_uv
from morpheus_core.geometry.mesh_hygiene import drop_floaters, topology_report
from morpheus_core.render.textured import load_textured, render_textured
from morpheus_core.runtime.devices import pick_device
from morpheus_core.texture import TextureField, TextureFieldConfig
from ops.engine.artifacts import load_module
from ops.engine.checks import ERROR, WARN, CheckSpec, CheckThresholds, QACheck, check
from ops.engine.previews import save_strip
from ops.engine.stage import Stage, StageContext, StageWork
from ops.engine.stage_job import StageResult
from ops.engine.target import ReferenceTarget, reference_psnr
from ops.stages.dmtet import MESH_FILE, TEXTURE_FILE, load_mesh

ASSET_GLB = "asset.glb"
ASSET_OBJ = "asset.obj"
TURNTABLE_FILE = "turntable.png"
REFERENCE_VIEW_FILE = "reference_view.png"
CODE_VERSION = "uv_bake-2"  # 2: drops floaters, records topology (kept as existing stores hold it)


@dataclass(frozen=True)
class BakeStageConfig:
    """The final stage: floaters dropped, UV unwrap and bake (``map``), GLB/OBJ export and previews."""

    map: BakeConfig = field(default_factory=BakeConfig)
    max_faces: int | None = None
    """Face budget of the export; None: the plan's decimation target, else ``bake.map.max_faces``."""
    write_obj: bool = True
    """Also write ``asset.obj`` (+ .mtl, .png) beside ``asset.glb``."""
    turntable_views: int = 8
    """Views of the exported GLB around the object (15° elevation) in ``turntable.png``."""
    preview_size: int = 160
    """Tile size (px) of ``turntable.png`` and ``reference_view.png``."""
    eval_resolution: int = 256
    """Render size (px) of the exported GLB for the reference-view PSNR and the turntable."""
    min_component_share: float = 0.01
    """Components below this share of the surface area are dropped before unwrapping (largest kept); 0 keeps all."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_component_share < 1.0:
            raise ValueError(f"bake.min_component_share must lie in [0, 1), got {self.min_component_share}")


def bake_asset(reference_dir: Path, dmtet_dir: Path, texture_dir: Path, out_dir: Path, cfg: BakeStageConfig,
               planned_max_faces: int | None = None, device: str = "auto") -> StageResult:
    """Drop floaters, unwrap + bake + export; metrics: faces, topology of the cleaned mesh (components
    before / after, floaters dropped and their area share, Euler number, genus, non-manifold and
    boundary edges, holes), watertightness, UV coverage, reference PSNR of the GLB."""
    dev = pick_device(device)
    source = load_mesh(Path(dmtet_dir) / MESH_FILE, dev)
    mesh, hygiene = drop_floaters(source, cfg.min_component_share)
    topology = topology_report(mesh)
    texture, _, _ = load_module(Path(texture_dir) / TEXTURE_FILE, TextureField, TextureFieldConfig, dev)
    limit = cfg.max_faces or planned_max_faces or cfg.map.max_faces
    bake_cfg = BakeConfig(**{**vars(cfg.map), "max_faces": limit})
    notes = []
    if hygiene["floaters_dropped"]:
        notes.append(f"dropped {hygiene['floaters_dropped']} floating component(s) below "
                     f"{cfg.min_component_share:.1%} of the surface area each ({hygiene['floater_area_share']:.2%} "
                     f"of the area in all); {hygiene['components']} component(s) kept")
    with torch.no_grad():
        baked = bake_uv(mesh, texture, bake_cfg)
    if baked.faces.shape[0] != mesh.num_faces:
        notes.append(f"decimated {mesh.num_faces} → {baked.faces.shape[0]} faces before unwrapping (budget {limit})")
    export_glb(baked, out_dir / ASSET_GLB)
    if cfg.write_obj:
        export_obj(baked, out_dir / ASSET_OBJ)

    asset = load_textured(out_dir / ASSET_GLB).to(dev)  # judge what was written, not the field
    r = cfg.eval_resolution
    target = ReferenceTarget.load(reference_dir, r, dev)
    with torch.no_grad():
        ref = render_textured(asset, target.camera, r, r).rgb_chw()
        views = render_textured(asset, turntable(cfg.turntable_views, 15.0).to(dev), r, r).rgb_chw()
    save_strip(out_dir / TURNTABLE_FILE, list(views), cfg.preview_size)
    save_strip(out_dir / REFERENCE_VIEW_FILE, [target.rgb[0], ref[0]], cfg.preview_size)
    metrics = {
        "faces": int(asset.faces.shape[0]), "source_faces": int(source.num_faces),
        "vertices": int(asset.vertices.shape[0]), "uv_coverage": round(baked.coverage, 4),
        "texture_size": bake_cfg.texture_size,
        # UV seams split the exported vertices, so closedness is judged on the mesh before unwrapping.
        "watertight": bool((mesh.topology.edge_counts == 2).all()),
        "ref_psnr": reference_psnr(ref, target),
        **hygiene,
        **{k: topology[k] for k in ("euler_number", "genus", "non_manifold_edges", "boundary_edges", "holes")},
    }
    return StageResult(metrics, "none (bake)", str(dev), notes)


def _build(ctx: StageContext, cfg: BakeStageConfig) -> StageWork:
    plan = ctx.plan
    faces = plan.export.value if plan is not None else None

    def body(out: Path, _ckpt: Path | None) -> StageResult:
        return bake_asset(ctx.dir("reference"), ctx.dir("dmtet"), ctx.dir("texture"), out, cfg, faces, ctx.device)

    return StageWork({"bake": cfg, "planned_faces": faces}, body)


REFERENCE_PSNR = CheckSpec("reference_psnr", ERROR, "the GLB's reference view reaches qa.min_ref_psnr dB")
UV_COVERAGE = CheckSpec("uv_coverage", WARN, "the UV atlas covers at least qa.min_uv_coverage of the texture")


def _judge(metrics: dict[str, Any], cfg: CheckThresholds) -> list[QACheck]:
    psnr = float(metrics.get("ref_psnr", float("nan")))
    cover = float(metrics.get("uv_coverage", 0.0))
    return [check(REFERENCE_PSNR, psnr >= cfg.min_ref_psnr, psnr, cfg.min_ref_psnr,
                  f"reference view {psnr:.1f} dB (minimum {cfg.min_ref_psnr:.1f} dB)"),
            check(UV_COVERAGE, cover >= cfg.min_uv_coverage, cover, cfg.min_uv_coverage,
                  f"UV atlas covers {cover:.1%} of the texture (minimum {cfg.min_uv_coverage:.1%})")]


STAGE = Stage(
    "bake", CODE_VERSION, config=BakeStageConfig, reads=("reference", "dmtet", "texture"),
    writes=(ASSET_GLB, ASSET_OBJ, "asset.mtl", "asset.png", TURNTABLE_FILE, REFERENCE_VIEW_FILE),
    preview=TURNTABLE_FILE, gpu=False, build=_build, checks=(REFERENCE_PSNR, UV_COVERAGE), judge=_judge,
    description="UV-unwrapped, baked, textured GLB (+ OBJ) with turntable and reference-view previews.")
