"""Final stage: UV-unwrap the mesh, bake the texture field, export GLB (+ OBJ) and previews.

The exported GLB is read back and rendered (not the field it came from), so the reference-view
PSNR and the turntable show what a user will load. Output: ``asset.glb``, ``asset.obj`` (+ .mtl,
.png), ``turntable.png`` (8 views around the object), ``reference_view.png`` (photo | asset).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch

from morpheus_core.cameras import turntable
from morpheus_core.geometry.mesh import edge_face_counts
from morpheus_core.render.textured import load_textured, render_textured
from morpheus_core.texture import BakeConfig, TextureField, TextureFieldConfig, bake_uv, export_glb, export_obj
from ops.dmtet import MESH_FILE, TEXTURE_FILE, load_mesh
from ops.stage_common import ReferenceTarget, StageResult, load_module, pick_device, reference_psnr, save_strip

ASSET_GLB = "asset.glb"
ASSET_OBJ = "asset.obj"
TURNTABLE_FILE = "turntable.png"
REFERENCE_VIEW_FILE = "reference_view.png"
CODE_VERSION = "uv_bake-1"


@dataclass(frozen=True)
class UVBakeConfig:
    """``max_faces``: None takes the plan's decimation target (else ``bake.max_faces``)."""

    bake: BakeConfig = field(default_factory=BakeConfig)
    max_faces: int | None = None
    write_obj: bool = True
    turntable_views: int = 8
    preview_size: int = 160
    eval_resolution: int = 256


def bake_asset(reference_dir: Path, dmtet_dir: Path, texture_dir: Path, out_dir: Path, cfg: UVBakeConfig,
               planned_max_faces: int | None = None, device: str = "auto") -> StageResult:
    """Unwrap + bake + export; metrics: faces, watertightness, UV coverage, reference PSNR of the GLB."""
    dev = pick_device(device)
    mesh = load_mesh(Path(dmtet_dir) / MESH_FILE, dev)
    texture, _, _ = load_module(Path(texture_dir) / TEXTURE_FILE, TextureField, TextureFieldConfig, dev)
    limit = cfg.max_faces or planned_max_faces or cfg.bake.max_faces
    bake_cfg = BakeConfig(**{**vars(cfg.bake), "max_faces": limit})
    notes = []
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
        "faces": int(asset.faces.shape[0]), "source_faces": int(mesh.num_faces),
        "vertices": int(asset.vertices.shape[0]), "uv_coverage": round(baked.coverage, 4),
        "texture_size": bake_cfg.texture_size,
        # UV seams split the exported vertices, so closedness is judged on the mesh before unwrapping.
        "watertight": bool((edge_face_counts(mesh)[1] == 2).all()),
        "ref_psnr": reference_psnr(ref, target),
    }
    return StageResult(metrics, "none (bake)", str(dev), notes)
