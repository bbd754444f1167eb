"""Score a reconstruction against its synthetic scene's ground truth over a ring of novel views.

The same views and metrics serve every stage's output (NeRF, DMTet mesh + texture field, the
refined texture, the exported GLB), so error can be followed through the pipeline:
novel-view PSNR and SSIM (whole image on white: silhouette and colour errors both count), detail
PSNR (the high band above ``detail_r`` alone: print, stripes, weave), high-frequency energy relative
to the truth (1 = as detailed), colour deviation against the truth (a*b*
histograms inside the objects, 0 = same colours), and Chamfer distance / F-score between the
visible surfaces.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch

from assets_store.store import Store
from benchmarks.scenes import Scene
from morpheus_core.cameras import Cameras, orbit
from morpheus_core.geometry.nerf import NerfConfig, NerfField
from morpheus_core.metrics.colour_deviation import colour_deviation
from morpheus_core.metrics.image import detail_psnr, hf_ratio, psnr, ssim
from morpheus_core.metrics.surface import surface_distance, visible_points
from morpheus_core.render.mesh_renderer import render_mesh
from morpheus_core.render.output import RenderOutput
from morpheus_core.render.textured import load_textured, render_textured
from morpheus_core.render.volume import VolumeRenderConfig, render_volume
from morpheus_core.texture import TextureField, TextureFieldConfig
from ops.engine.artifacts import load_module
from ops.stages.dmtet import MESH_FILE, TEXTURE_FILE, load_mesh
from ops.stages.nerf import NERF_FILE

RenderFn = Callable[[Cameras, int], RenderOutput]


@dataclass(frozen=True)
class EvalConfig:
    """Views: ``azimuths`` evenly spaced at each of ``elevations`` (degrees), the reference view
    (0°, 0°) left out; ``fscore_threshold`` in world units (objects span ≈ 1.46)."""

    azimuths: int = 8
    elevations: tuple[float, ...] = (0.0, 20.0)
    resolution: int = 128
    fscore_threshold: float = 0.05
    hf_cutoff: float = 0.5
    detail_r: float = 0.6  # the paper's r: the band only the 2D prior knows


@dataclass(frozen=True)
class Reconstruction:
    """How to render one reconstruction; volume renders store opacity-weighted depth."""

    render: RenderFn
    weighted_depth: bool = False


def novel_cameras(cfg: EvalConfig) -> Cameras:
    elev, azim = [], []
    for e in cfg.elevations:
        for i in range(cfg.azimuths):
            a = i * 360.0 / cfg.azimuths
            if e == 0.0 and i == 0:
                continue  # the reference view is not a novel view
            elev.append(e)
            azim.append(a - 360.0 if a > 180.0 else a)
    return orbit(elev, azim)


def _mean(values: list[float | None]) -> float | None:
    kept = [v for v in values if v is not None and math.isfinite(v)]
    return sum(kept) / len(kept) if kept else None


@torch.no_grad()
def evaluate(recon: Reconstruction, scene: Scene, cfg: EvalConfig | None = None) -> dict[str, float | None]:
    """Novel-view and geometry errors of ``recon`` against ``scene`` (see the module docstring)."""
    cfg = cfg or EvalConfig()
    cams, r = novel_cameras(cfg), cfg.resolution
    truth, pred = scene.render(cams, r), recon.render(cams, r)
    if not bool(torch.isfinite(pred.rgb).all()):
        raise ValueError("the reconstruction renders NaN/Inf")
    gt_rgb, pr_rgb = truth.rgb_chw().float().cpu(), pred.rgb_chw().float().cpu()
    gt_a, pr_a = truth.opacity_chw().float().cpu(), pred.opacity_chw().float().cpu()
    n = len(cams)
    views = range(n)
    ref_cam = orbit(0.0, 0.0)
    ref_truth, ref_pred = scene.render(ref_cam, r), recon.render(ref_cam, r)
    distance = surface_distance(visible_points(pred, cams.to(device=pred.depth.device),
                                               weighted_depth=recon.weighted_depth).cpu(),
                                visible_points(truth, cams).cpu(), cfg.fscore_threshold)
    return {
        "novel_psnr": _mean([psnr(pr_rgb[i], gt_rgb[i]) for i in views]),
        "detail_psnr": _mean([detail_psnr(pr_rgb[i], gt_rgb[i], cfg.detail_r) for i in views]),
        "novel_ssim": _mean([ssim(pr_rgb[i:i + 1], gt_rgb[i:i + 1]) for i in views]),
        "hf_ratio": _mean([hf_ratio(pr_rgb[i:i + 1], gt_rgb[i:i + 1], cfg.hf_cutoff, pr_a[i:i + 1], gt_a[i:i + 1])
                           for i in views]),
        "colour_deviation": _mean([colour_deviation(pr_rgb[i:i + 1], pr_a[i:i + 1], gt_rgb[i:i + 1], gt_a[i:i + 1])
                                   for i in views]),
        "ref_psnr": psnr(ref_pred.rgb.float().cpu(), ref_truth.rgb.float().cpu()),
        "chamfer": distance.chamfer,
        "fscore": distance.fscore,
    }


# -- loading each stage's output as a Reconstruction ------------------------------------------


def nerf_output(store: Store, key: str, render: VolumeRenderConfig, device: torch.device) -> Reconstruction:
    field, _, _ = load_module(store.stage_dir(key, "nerf") / NERF_FILE, NerfField, NerfConfig, device)
    cfg = VolumeRenderConfig(n_samples=render.n_samples, stratified=False, with_normals=False,
                             chunk_points=render.chunk_points)

    def render(cams: Cameras, r: int) -> RenderOutput:
        # One view at a time: all novel views at once hold every ray's samples (~50 GiB at the paper's
        # 256 per ray), which ran eight benchmark processes sharing an H200 out of memory.
        cams = cams.to(device=device)
        return RenderOutput.cat([render_volume(field, cams[i], r, r, cfg, 1.0) for i in range(len(cams))])

    return Reconstruction(render, weighted_depth=True)


def mesh_output(store: Store, key: str, texture_stage: str, device: torch.device) -> Reconstruction:
    """The DMTet mesh coloured by the texture field of ``texture_stage`` (``dmtet`` or ``texture``)."""
    mesh = load_mesh(store.stage_dir(key, "dmtet") / MESH_FILE, device)
    texture, _, _ = load_module(store.stage_dir(key, texture_stage) / TEXTURE_FILE, TextureField,
                                TextureFieldConfig, device)
    return Reconstruction(lambda cams, r: render_mesh(mesh, cams.to(device=device), r, r, texture))


def glb_output(path: Path, device: torch.device) -> Reconstruction:
    asset = load_textured(path).to(device)
    return Reconstruction(lambda cams, r: render_textured(asset, cams.to(device=device), r, r))
