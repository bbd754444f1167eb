"""The QA gate: does an asset ship? Checks on every stage's output, and the final ``qa`` stage.

Each check has a severity: ``error`` checks decide pass/fail, ``warn`` checks flag an asset for a
look without failing it. Thresholds come from ``QAConfig`` (``--set qa.min_ref_psnr=18``). The
checks of the producing stages are pure functions of their manifest metrics, so the Dagster
assets and the QA report agree by construction; the ``qa`` stage re-loads the written GLB and
measures it on its own (``morpheus_core.metrics.image``: reference-view PSNR / SSIM inside and outside
the mask, silhouette IoU, high-frequency ratio; ``.colour_deviation`` over a turntable; ``.mesh_health``;
its parts against the photo's mask and the NeRF's silhouettes (``compare_with_nerf``);
``morpheus_core.metrics.weighted``: LPIPS, CLIP similarity, CLIP-IQA, MANIQA when their weights
are installed, else recorded as skipped) rather than trusting the numbers the bake reported.

Output of the ``qa`` stage: ``qa.json`` (verdict, reasons, every check and metric, the weighted
metrics' status), ``turntable.png`` (a strip of ``strip_views`` views) and ``turntable.gif`` (all
``turntable_views`` views, animated).
"""

from __future__ import annotations

import io
import json
import os
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

from assets_store.atomic import atomic_write_bytes, atomic_write_text
from morpheus_core.cameras import turntable
from morpheus_core.metrics.colour_deviation import colour_deviation
from morpheus_core.metrics.image import hf_ratio, mask_iou, masked_psnr, masked_ssim, ssim
from morpheus_core.metrics.mesh_health import mesh_health
from morpheus_core.metrics.weighted import WeightedMetricsConfig, compute_weighted_metrics
from morpheus_core.render.textured import TexturedMesh, load_textured, render_textured
from morpheus_core.runtime.devices import pick_device
from morpheus_core.segmentation.part_silhouettes import (
    PartComparison,
    asset_silhouettes,
    compare_part_silhouettes,
    count_parts,
    nerf_silhouettes,
    part_cameras,
)
from ops.engine.checks import ERROR, QA_FILE, WARN, CheckSpec, QACheck, QAReport, check, verdict
from ops.engine.previews import save_strip, to_uint8
from ops.engine.progress import Heartbeat
from ops.engine.stage import Stage, StageContext, StageWork
from ops.engine.stage_job import StageResult
from ops.engine.target import ReferenceTarget, reference_psnr
from ops.engine.viewer_page import VIEWER_DIR, VIEWER_FILE, ViewerPage, vendor_viewer, write_viewer
from ops.stages.bake import ASSET_GLB
from ops.stages.export import MODEL_GLB, MODEL_USDZ, MODEL_WEB_GLB
from ops.stages.nerf import NERF_FILE, load_nerf

# The qa stage's own checks (it judges its own output; the producing stages declare theirs on their ``Stage``).
QA_CHECKS: dict[str, CheckSpec] = {s.name: s for s in (
    CheckSpec("asset_finite", ERROR, "every vertex, UV and texel of the GLB is finite"),
    CheckSpec("mask_iou", ERROR, "the GLB's reference silhouette matches the photo's mask (IoU)"),
    CheckSpec("watertight", WARN, "the mesh is closed (an error when qa.require_watertight)"),
    CheckSpec("degenerate_faces", WARN, "at most qa.max_degenerate_fraction of the faces have ~zero area"),
    CheckSpec("colour_deviation", WARN, "novel views keep the photo's colours (a*b* histogram distance "
                                         "at most qa.max_colour_deviation)"),
    CheckSpec("hf_ratio", WARN, "novel views keep at least qa.min_hf_ratio of the photo's high-frequency "
                                 "detail"),
    CheckSpec("part_count", WARN, "the GLB has no more connected components than the photo's mask has "
                                  "silhouette parts (pieces of at least qa.min_part_share of its area)"),
    CheckSpec("parts_kept", ERROR, "from qa.part_views novel views, no region the NeRF shows larger than "
                                   "qa.max_missing_part_share of its silhouette is missing from the GLB, "
                                   "and the silhouette IoU stays at least qa.min_part_iou"),
    CheckSpec("verdict", ERROR, "no error-severity check failed in any stage"))}

QA_TURNTABLE_FILE = "turntable.png"
QA_TURNTABLE_GIF = "turntable.gif"
CODE_VERSION = "qa-4"  # 3: part_count and parts_kept; 4: the export's checks and viewer.html


@dataclass(frozen=True)
class QAConfig:
    """Thresholds of the QA checks and the evaluation set-up. Defaults are the paper's evaluation
    (reference view at 800 px, 100 turntable views); presets shrink them. Thresholds sit below
    what the draft preset reaches on the bundled photos (GLB reference PSNR 19–23 dB, mask IoU
    > 0.9), so a failing check means a broken asset, not a coarse one.

    ``parts_kept`` renders the NeRF and the GLB from ``part_views`` novel views and compares their
    silhouettes (``part_*``, ``max_missing_part_share``, ``min_part_iou``)."""

    min_ref_psnr: float = 15.0
    """Error below: the exported GLB's reference-view PSNR (dB) against the photo (check ``bake.reference_psnr``)."""
    min_mask_iou: float = 0.80
    """Error below: IoU (0–1) of the GLB's reference-view silhouette with the photo's mask."""
    min_uv_coverage: float = 0.25
    """Warning below: share (0–1) of the texture the UV atlas covers."""
    min_area_fraction: float = 0.02
    """Warning below: share of the photo the object's mask covers (check ``reference.object_size``)."""
    max_guard_events: int = 10
    """Warning above: NaN/Inf guard events (skipped or rolled-back steps, restores) of an optimising stage."""
    max_size_disagreement: float = 0.15
    """Warning above: relative gap of a catalog dimension from the mesh sized by another (``export.true_size``)."""
    max_colour_deviation: float = 0.5
    """Warning above: 1 − Bhattacharyya coefficient (0–1) of turntable vs photo a*b* histograms (colour drift)."""
    min_hf_ratio: float = 0.05
    """Warning below: turntable views' high-frequency energy share relative to the photo's (1: as detailed)."""
    max_degenerate_fraction: float = 0.01
    """Warning above: share of faces with ~zero area (≤ 1e-12 × bounding-box diagonal²) or repeated corners."""
    require_watertight: bool = False
    """Make an open mesh (edges with other than two faces) an error instead of a warning."""
    eval_resolution: int = 800
    """Render size (px) of the GLB's reference view for PSNR, SSIM and mask IoU (the paper's evaluation: 800)."""
    turntable_views: int = 100
    """Turntable views of the GLB for colour deviation, HF ratio, learned metrics, the GIF (the paper: 100)."""
    turntable_resolution: int = 256
    """Render size (px) of the turntable views."""
    turntable_elevation: float = 15.0
    """Elevation (degrees) of the turntable and of the ``parts_kept`` views."""
    render_chunk: int = 8
    """Turntable views rendered per batch: bounds peak memory, not the result."""
    preview_size: int = 128
    """Tile size (px) of ``turntable.png`` and frame size of ``turntable.gif``."""
    strip_views: int = 8
    """Views (evenly picked from the turntable) in the ``turntable.png`` strip."""
    weighted_metrics: bool = True
    """Compute the learned metrics (LPIPS, CLIP similarity, CLIP-IQA, MANIQA) whose weights are installed."""
    models_root: str | None = None
    """Folder of the learned metrics' weights; None: ``$MORPHEUS_MODELS``, else the default root."""
    min_part_share: float = 0.01
    """Smallest share of the photo mask's area that counts as a silhouette part (smaller: segmentation specks)."""
    part_views: int = 6
    """Novel views (at ``turntable_elevation``) from which ``parts_kept`` compares NeRF and GLB silhouettes."""
    part_resolution: int = 96
    """Render size (px, ≥ 16) of the ``parts_kept`` silhouettes."""
    part_samples: int = 64
    """Samples per ray of the NeRF's ``parts_kept`` silhouettes."""
    part_opening: int = 1
    """NeRF/GLB disagreements thinner than 2·this + 1 px (outline rings, not parts) are ignored."""
    part_margin: int = 0
    """What the NeRF shows within this many px of the GLB's silhouette is ignored (0: none; thin meshes fail)."""
    max_missing_part_share: float = 0.1
    """Error above: a region the NeRF shows and the GLB lacks, as a share of that view's NeRF silhouette."""
    min_part_iou: float = 0.5
    """Error below: NeRF vs GLB silhouette IoU in any ``parts_kept`` view."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_mask_iou <= 1.0 or not 0.0 <= self.min_uv_coverage <= 1.0:
            raise ValueError("qa.min_mask_iou and qa.min_uv_coverage must lie in [0, 1]")
        if min(self.eval_resolution, self.turntable_resolution) < 16 or self.turntable_views < 1:
            raise ValueError("qa.eval_resolution and qa.turntable_resolution must be >= 16, qa.turntable_views >= 1")
        if self.render_chunk < 1 or self.strip_views < 1:
            raise ValueError("qa.render_chunk and qa.strip_views must be >= 1")
        if min(self.part_views, self.part_samples) < 1 or self.part_resolution < 16:
            raise ValueError("qa.part_views and qa.part_samples must be >= 1, qa.part_resolution >= 16")
        if min(self.part_opening, self.part_margin) < 0:
            raise ValueError("qa.part_opening and qa.part_margin must be >= 0")
        for name in ("min_part_share", "max_missing_part_share", "min_part_iou"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"qa.{name} must lie in [0, 1], got {getattr(self, name)}")


def _render_views(asset: Any, cameras: Any, size: int, chunk: int) -> tuple[torch.Tensor, torch.Tensor]:
    """RGB (N×3×S×S, on white) and opacity (N×1×S×S) of many views, ``chunk`` views at a time."""
    rgbs, alphas = [], []
    with torch.no_grad():
        for i in range(0, len(cameras), chunk):
            out = render_textured(asset, cameras[i:i + chunk], size, size)
            rgbs.append(out.rgb_chw().float().cpu())
            alphas.append(out.opacity_chw().float().cpu())
    return torch.cat(rgbs), torch.cat(alphas)


def _save_gif(path: Path, frames: torch.Tensor, size: int) -> Path:
    """An animated turntable (loops forever, 10 s per revolution) — what people actually watch."""
    small = F.interpolate(frames.float(), size=(size, size), mode="bilinear", align_corners=False)
    images = [Image.fromarray(to_uint8(f)) for f in small]
    duration = max(20, int(10_000 / len(images)))
    buf = io.BytesIO()
    images[0].save(buf, format="GIF", save_all=True, append_images=images[1:], duration=duration, loop=0,
                   optimize=True)
    return atomic_write_bytes(Path(path), buf.getvalue())


def _weighted(cfg: QAConfig, photo: torch.Tensor, mask: torch.Tensor, views: torch.Tensor,
              ref_render: torch.Tensor, device: str) -> dict[str, dict[str, Any]]:
    if not cfg.weighted_metrics:
        return {}
    wcfg = WeightedMetricsConfig(models_root=Path(cfg.models_root) if cfg.models_root else None,
                                 device="cpu" if device == "auto" else device)
    results = compute_weighted_metrics(photo, mask, views, wcfg, reference_render=ref_render)
    return {name: {"value": r.value, "status": r.status, "detail": r.detail} for name, r in results.items()}


# ``parts_kept``: the GLB's silhouettes against the NeRF's from a few novel views. The NeRF is what the photo and
# the prior agreed on before DMTet's fixed iso-level and floater removal; where it is opaque and the mesh is not,
# from any side, the mesh lost a part.
def compare_with_nerf(asset: TexturedMesh, nerf_dir: Path | None, views: int, resolution: int, n_samples: int,
                      elevation_deg: float, opening: int, margin: int, device: torch.device) -> PartComparison | None:
    """The GLB against the NeRF from ``views`` novel views; None when there is no NeRF output (an
    asset refined from an existing mesh has no NeRF stage)."""
    if nerf_dir is None or not (Path(nerf_dir) / NERF_FILE).is_file():
        return None
    nerf, occupancy = load_nerf(Path(nerf_dir), device)
    cameras = part_cameras(views, elevation_deg).to(device)
    reference = nerf_silhouettes(nerf, occupancy, cameras, resolution, n_samples)
    return compare_part_silhouettes(reference, asset_silhouettes(asset, cameras, resolution), opening, margin)


def run_qa(reference_dir: Path, glb_path: Path, out_dir: Path, cfg: QAConfig,
           upstream: dict[str, list[QACheck]], prior: str = "", device: str = "auto",
           nerf_dir: Path | None = None,
           phase: Callable[[str], None] | None = None) -> tuple[StageResult, QAReport]:
    """Measure the written GLB and gather every stage's checks into ``qa.json``; returns the stage's result
    and the report written.

    Metrics: reference view (at ``eval_resolution``) PSNR and SSIM, overall and inside / outside
    the photo's mask, silhouette IoU; over a turntable of ``turntable_views``: high-frequency
    energy relative to the photo and colour deviation (a*b* histograms inside the masks); mesh
    health (components, watertight, winding, Euler number, degenerate faces, UV coverage, texel
    density, seam leakage); the learned metrics whose weights are installed (others are recorded
    as skipped). ``upstream`` maps stage → its checks, judged from its manifest metrics with this config's
    thresholds (``StageContext.stage_checks``), so the verdict is one consistent decision.
    Parts: the photo mask's silhouette parts against the GLB's components, and the GLB's
    silhouettes against the NeRF's in ``nerf_dir`` (the ``nerf`` stage's output; None when the
    asset has no NeRF stage, which leaves ``parts_kept`` unmeasured). ``phase`` hears which
    measurement starts (a ``Heartbeat``'s ``set_phase``: QA takes minutes on a CPU at paper sizes).
    """
    phase = phase or (lambda _: None)
    dev = pick_device(device)
    out_dir = Path(out_dir)
    phase("loading the GLB, mesh health")
    asset = load_textured(glb_path).to(dev)
    checks: dict[str, list[QACheck]] = {s: c for s, c in upstream.items() if c}
    finite = all(bool(torch.isfinite(t).all()) for t in (asset.vertices, asset.uvs, asset.texture))
    own: list[QACheck] = [check(QA_CHECKS["asset_finite"], finite, finite, True,
                                 "finite" if finite else "the GLB holds NaN/Inf values")]
    health = mesh_health(asset.vertices.cpu(), asset.faces.cpu(), asset.uvs.cpu(), asset.texture.cpu())
    metrics: dict[str, Any] = {k: v for k, v in health.items()}
    weighted: dict[str, dict[str, Any]] = {}
    if finite and health["faces"]:
        r = cfg.eval_resolution
        phase(f"reference view at {r} px")
        target = ReferenceTarget.load(reference_dir, r, dev)
        ref_rgb, ref_alpha = _render_views(asset, target.camera, r, 1)
        photo, mask = target.rgb[0].float().cpu(), target.mask[0].float().cpu()
        metrics["ref_psnr"] = reference_psnr(ref_rgb.to(dev), target)
        metrics["psnr_in"], metrics["psnr_out"] = masked_psnr(ref_rgb[0], photo, mask)
        metrics["ssim"] = ssim(ref_rgb[0], photo)
        metrics["ssim_in"], metrics["ssim_out"] = masked_ssim(ref_rgb[0], photo, mask)
        metrics["mask_iou"] = round(mask_iou(ref_alpha[0], mask), 4)
        t = cfg.turntable_resolution
        phase(f"{cfg.turntable_views} turntable views at {t} px")
        views, alphas = _render_views(asset, turntable(cfg.turntable_views, cfg.turntable_elevation).to(dev), t,
                                      cfg.render_chunk)
        small_photo = F.interpolate(photo[None], size=(t, t), mode="area")[0]
        small_mask = F.interpolate(mask[None], size=(t, t), mode="area")[0]
        metrics["hf_ratio"] = hf_ratio(views, small_photo, mask=alphas, reference_mask=small_mask)
        metrics["colour_deviation"] = colour_deviation(views, alphas, photo, mask)
        strip = torch.linspace(0, len(views) - 1, min(cfg.strip_views, len(views))).round().long()
        save_strip(out_dir / QA_TURNTABLE_FILE, list(views[strip]), cfg.preview_size)
        _save_gif(out_dir / QA_TURNTABLE_GIF, views, cfg.preview_size)
        phase("learned metrics (those whose weights are installed)")
        weighted = _weighted(cfg, photo, mask, views, ref_rgb[0], device)
        for name, w in weighted.items():
            metrics[name] = w["value"]
        iou = metrics["mask_iou"]
        own.append(check(QA_CHECKS["mask_iou"], iou >= cfg.min_mask_iou, iou, cfg.min_mask_iou,
                          f"silhouette IoU {iou:.3f} (minimum {cfg.min_mask_iou})"))
        dev_c = metrics["colour_deviation"]
        own.append(check(QA_CHECKS["colour_deviation"], dev_c is not None and dev_c <= cfg.max_colour_deviation,
                          dev_c, cfg.max_colour_deviation,
                          "not measured (empty masks)" if dev_c is None else
                          f"a*b* histogram distance {dev_c:.3f} (maximum {cfg.max_colour_deviation})"))
        hf = metrics["hf_ratio"]
        own.append(check(QA_CHECKS["hf_ratio"], hf is None or hf >= cfg.min_hf_ratio, hf, cfg.min_hf_ratio,
                          "not measured (flat photo)" if hf is None else
                          f"novel views keep {hf:.2f}× the photo's high-frequency share (minimum {cfg.min_hf_ratio})"))
        phase("parts against the photo's mask and the NeRF's silhouettes")
        own += _part_checks(cfg, asset, mask[0] > 0.5, int(health["components"] or 0), nerf_dir, dev, metrics)
    else:
        reason = "not measured: non-finite asset" if not finite else "not measured: the GLB has no faces"
        for name in ("mask_iou", "colour_deviation", "hf_ratio", "part_count", "parts_kept"):
            own.append(check(QA_CHECKS[name], False, None, None, reason))
    closed = bool(health["watertight"])
    own.append(check(QA_CHECKS["watertight"], closed, closed, True,
                      "closed" if closed else "the mesh has open edges", ERROR if cfg.require_watertight else WARN))
    degenerate = (health["degenerate_faces"] or 0) / max(1, health["faces"] or 0)
    own.append(check(QA_CHECKS["degenerate_faces"], degenerate <= cfg.max_degenerate_fraction, round(degenerate, 5),
                      cfg.max_degenerate_fraction, f"{degenerate:.2%} of the faces are degenerate"))
    everything = [c for cs in checks.values() for c in cs] + own
    decision, reasons = verdict(everything)
    own.append(check(QA_CHECKS["verdict"], decision != "fail", decision, "pass or warn",
                      "; ".join(reasons) if reasons else "every check passed"))
    checks["qa"] = own
    report = QAReport(decision, reasons, {s: [asdict(c) for c in cs] for s, cs in checks.items()},
                      _finite_json(metrics), prior, weighted=weighted)
    atomic_write_text(out_dir / QA_FILE, json.dumps(asdict(report), indent=2, sort_keys=True, default=str))
    summary = {k: v for k, v in _finite_json(metrics).items() if isinstance(v, (int, float, bool)) or v is None}
    return StageResult({**summary, "verdict": decision, "failed_checks": len(reasons)}, "none (qa)", str(dev)), report


def _part_checks(cfg: QAConfig, asset: Any, mask: torch.Tensor, components: int, nerf_dir: Path | None,
                 dev: torch.device, metrics: dict[str, Any]) -> list[QACheck]:
    """``part_count`` and ``parts_kept``; records ``mask_parts`` and the NeRF comparison in ``metrics``."""
    parts = count_parts(mask, cfg.min_part_share)
    metrics["mask_parts"] = parts
    out = [check(QA_CHECKS["part_count"], components <= parts, components, parts,
                  f"the GLB has {components} connected component(s), the photo's mask {parts} silhouette part(s)")]
    spec = QA_CHECKS["parts_kept"]
    threshold = {"max_missing_part_share": cfg.max_missing_part_share, "min_part_iou": cfg.min_part_iou}
    found = compare_with_nerf(asset, nerf_dir, cfg.part_views, cfg.part_resolution, cfg.part_samples,
                              cfg.turntable_elevation, cfg.part_opening, cfg.part_margin, dev)
    if found is None:
        return [*out, check(spec, True, None, threshold, "not measured: no NeRF stage output")]
    metrics["part_iou_min"] = round(found.iou_min, 4)
    metrics["part_iou_mean"] = round(found.iou_mean, 4)
    metrics["missing_part_share_max"] = round(found.missing_share_max, 4)
    lost = found.missing_share_max > cfg.max_missing_part_share
    apart = found.iou_min < cfg.min_part_iou
    view = max(range(len(found.missing_share)), key=found.missing_share.__getitem__)
    message = (f"largest region the NeRF shows and the GLB lacks: {found.missing_share_max:.1%} of the NeRF "
               f"silhouette (view {view + 1} of {len(found.iou)}; maximum {cfg.max_missing_part_share:.0%}); "
               f"silhouette IoU min {found.iou_min:.3f} (minimum {cfg.min_part_iou}), mean {found.iou_mean:.3f}")
    value = {"missing_part_share_max": metrics["missing_part_share_max"], "part_iou_min": metrics["part_iou_min"]}
    return [*out, check(spec, not (lost or apart), value, threshold,
                         ("lost a part: " if lost else "") + message)]


def _finite_json(metrics: dict[str, Any]) -> dict[str, Any]:
    """JSON has no NaN/Inf: non-finite numbers become None (the checks already failed on them)."""
    return {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in metrics.items()}


def write_asset_viewer(out: Path, report: QAReport, final_dir: Path, reference_dir: Path, export_dir: Path, key: str,
                       export: dict[str, Any]) -> str | None:
    """``viewer.html``: the web GLB at its real size, the photo, the dimensions and ``report``'s verdict. Links
    are relative to where the page will live (``final_dir``, beside the other stages' folders); the viewer's
    script is vendored into the store once. Returns why the page cannot show the model, None when it can."""
    photos = sorted(Path(reference_dir).glob("rgba_*.png"))
    up = os.path.relpath(export_dir, final_dir)
    page = ViewerPage(
        title=export.get("sku") or key, web_glb=(Path(export_dir) / MODEL_WEB_GLB).read_bytes(),
        glb_href=f"{up}/{MODEL_GLB}", usdz_href=f"{up}/{MODEL_USDZ}" if export.get("usdz_bytes") else None,
        photo_href=os.path.relpath(photos[-1], final_dir) if photos else None,
        script_dir_href=os.path.relpath(Path(final_dir).parent.parent / VIEWER_DIR, final_dir),
        size_mm={d: export[f"{d}_mm"] for d in ("width", "height", "depth") if f"{d}_mm" in export},
        verdict=report.verdict, reasons=report.reasons, scale_source=export.get("scale_source", ""),
        sku=export.get("sku", ""))
    write_viewer(Path(out) / VIEWER_FILE, page)
    return vendor_viewer(Path(final_dir).parent.parent)


def _build(ctx: StageContext, cfg: QAConfig) -> StageWork:
    producers = [s for s in ctx.stages if s != "qa"]
    # Every producer is an input, the NeRF included (parts_kept renders it), so a changed NeRF
    # re-runs QA; with --init-mesh there is no NeRF stage and parts_kept is not measured.
    nerf_dir = ctx.dir("nerf") if "nerf" in producers else None

    def body(out: Path, _ckpt: Path | None) -> StageResult:
        upstream = {s: ctx.stage_checks(s, cfg) for s in producers}
        prior = ctx.upstream("texture").prior
        with Heartbeat(ctx.progress(), "qa", announce=True) as beat:  # one line at least every 10 s
            result, report = run_qa(ctx.dir("reference"), ctx.dir("bake") / ASSET_GLB, out, cfg, upstream, prior,
                                    ctx.device, nerf_dir, beat.set_phase)
        if "export" in producers:
            missing = write_asset_viewer(out, report, ctx.dir("qa"), ctx.dir("reference"), ctx.dir("export"), ctx.key,
                                         ctx.upstream("export").metrics)
            if missing:
                result.notes.append(f"viewer.html cannot show the model: {missing}")
        return result

    return StageWork({"qa": cfg}, body)


STAGE = Stage(
    "qa", CODE_VERSION, config=QAConfig, reads=("reference", "nerf", "dmtet", "texture", "bake", "export"),
    writes=(QA_FILE, QA_TURNTABLE_FILE, QA_TURNTABLE_GIF, VIEWER_FILE), preview=QA_TURNTABLE_FILE, gpu=False,
    build=_build, checks=tuple(QA_CHECKS.values()),
    description="QA of the written GLB: reference-view PSNR, silhouette IoU, finiteness, mesh health, its parts "
                "against the photo's mask and the NeRF's silhouettes, and every stage's checks; verdict "
                "pass / warn / fail with reasons (qa.json); viewer.html shows the asset at its real size.")
