"""Stage 1b: NeRF → DMTet, then optimise the mesh under the 3D prior (SDS, t ∈ [0.02, 0.5]).

The SDF starts from the NeRF density (inside where density > 25) on the grid the plan chose; a
texture field (hash grid + MLP) is warm-started from the NeRF's albedo around the surface and
then trained with the geometry. Losses: reference guidance + mask BCE on the reference view, the
3D prior on random views, Laplacian smoothness, normal consistency and the SDF sign regulariser
(every term a mean, balanced as in ``morpheus_core.guidance.loss_balance``).

``--init-mesh`` (refining an existing asset, paper §5.6): the SDF sign comes from the mesh's
winding number and the texture field is fitted to colours sampled from its baked texture.
Output: ``mesh.safetensors`` (vertices, faces), ``texture_field.safetensors``, ``dmtet.safetensors`` (SDF and
deformation, rebuildable with its grid config), preview, run log.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from assets_store.atomic import atomic_write
from assets_store.hashing import file_sha256
from morpheus_core.export.uv_bake import cluster_decimate
from morpheus_core.geometry.marching_tets import EmptySurfaceError, NonFiniteFieldError
from morpheus_core.geometry.mesh import Mesh, laplacian_smoothness, normal_consistency
from morpheus_core.geometry.tet_surface import DMTet, DMTetConfig
from morpheus_core.geometry.winding import winding_number
from morpheus_core.guidance.loss_balance import mask_bce
from morpheus_core.guidance.presets import DMTET_GUIDANCE, GuidanceSettings
from morpheus_core.nerf_to_dmtet import (
    Conversion,
    ConversionConfig,
    Silhouettes,
    convert,
    mesh_silhouettes,
    silhouette_iou,
)
from morpheus_core.render.mesh_renderer import render_mesh, render_mesh_groups
from morpheus_core.render.textured import load_textured, sample_surface
from morpheus_core.runtime.devices import pick_device
from morpheus_core.texture import TextureField, TextureFieldConfig, fit_colour_field, jittered_surface_points
from ops.engine.artifacts import RUNLOG_FILE, require_finite_output, save_module, write_log
from ops.engine.checks import (
    ERROR,
    STABLE_OPTIMISATION,
    CheckSpec,
    CheckThresholds,
    QACheck,
    check,
    stable_optimisation,
)
from ops.engine.guided_task import GuidedTask, RenderedStep
from ops.engine.loop import BadStep, LoopConfig, LoopResult
from ops.engine.previews import PREVIEW_FILE, save_stage_preview
from ops.engine.priors import PriorsConfig, PriorSuite, build_suite
from ops.engine.progress import Heartbeat, ProgressFn
from ops.engine.render_phases import Phase, RenderSchedule, check_phases
from ops.engine.stage import Stage, StageContext, StageWork, optimising
from ops.engine.stage_job import StageJob, StageResult, loop_metrics
from ops.engine.target import ReferenceTarget, novel_cameras
from ops.stages.nerf import load_nerf

MESH_FILE = "mesh.safetensors"
TEXTURE_FILE = "texture_field.safetensors"
DMTET_FILE = "dmtet.safetensors"
CODE_VERSION = "dmtet-2"  # 2: loss balance, silhouette-chosen conversion, NeRF silhouettes


@dataclass(frozen=True)
class DMTetStageConfig:
    """Stage 1b: the tet grid, its optimisation schedule and loss weights, and the texture field."""

    loop: LoopConfig = field(default_factory=lambda: LoopConfig(steps=5000, checkpoint_every=500, log_every=50))
    resolution: int = 512
    """Render size (px) of the reference and novel views each step (the paper: 512)."""
    n_views: int = 1
    """Random orbit views rendered for the 3D prior each step, besides the reference view."""
    phases: tuple[Phase, ...] = ()
    """Coarse render phases before ``resolution`` and ``n_views`` (``ops.engine.render_phases``): each
    ``{until, resolution, n_views}`` holds while the step is below ``until`` × the stage's steps."""
    grid: int | None = None
    """Tet grid resolution (cells per side, ≥ 8); None: the plan's choice (else ``max_grid``); capped at max_grid."""
    max_grid: int = 128
    """Largest tet grid (cells per side), whatever ``grid`` or the plan asks for (the paper: 128)."""
    conversion: ConversionConfig = field(default_factory=ConversionConfig)
    deform_scale: float = 0.5
    """Largest vertex offset, in cells per axis (0–1): half a cell keeps axis neighbours from passing each other."""
    texture_field: TextureFieldConfig = field(default_factory=TextureFieldConfig)
    guidance: GuidanceSettings = field(default_factory=lambda: DMTET_GUIDANCE)
    """The paper's stage 1b: 3D prior SDS, t ∈ [0.02, 0.5]."""
    lr_sdf: float = 1e-3
    """Adam learning rate of the SDF values at the grid vertices."""
    lr_deform: float = 1e-2
    """Adam learning rate of the grid vertices' deformations (before their tanh)."""
    lr_grid: float = 1e-2
    """Adam learning rate of the texture field's hash-grid tables."""
    lr_mlp: float = 1e-3
    """Adam learning rate of the texture field's MLP."""
    mask_weight: float = 1.0
    """Weight of the reference view's opacity-vs-mask BCE (a mean over pixels, as the official code)."""
    # Against the mean reference terms these keep the weights the regularisers had against the summed
    # ones before the official balance (÷ 3 channels).
    laplacian_weight: float = 3.0
    """Weight of the mesh's uniform-Laplacian smoothness term (a mean over vertices)."""
    normal_consistency_weight: float = 0.03
    """Weight of the normal consistency term: 1 − cos between adjacent face normals, a mean over edges."""
    sdf_reg_weight: float = 0.003
    """Weight of the SDF sign-change regulariser over crossing grid edges (against floaters, spurious flips)."""
    nerf_silhouette_weight: float = 1.0
    """BCE weight (a mean) of the NeRF's check-view silhouettes, one view a step: holds the NeRF's geometry."""
    colour_fit_steps: int = 300
    """Adam steps fitting the texture field to the NeRF's albedo (or the init mesh's colours) before optimising."""
    colour_fit_points: int = 1 << 15
    """Surface points sampled (jittered ±2 cells around the NeRF mesh) for that colour fit."""
    init_mesh_max_faces: int = 3000
    """``--init-mesh`` is decimated to this many faces for its winding number (O(points × faces))."""
    preview_size: int = 192
    """Tile size (px) of ``preview.png`` (photo | reference render | three orbit views)."""

    def __post_init__(self) -> None:
        if self.resolution < 8 or self.n_views < 1 or self.max_grid < 4:
            raise ValueError("resolution must be ≥ 8, n_views ≥ 1 and max_grid ≥ 4")
        check_phases(self.phases)


def choose_grid(cfg: DMTetStageConfig, planned: int | None) -> int:
    grid = cfg.grid if cfg.grid is not None else (planned or cfg.max_grid)
    return max(8, min(grid, cfg.max_grid))


class DMTetTask(GuidedTask):
    def __init__(self, cfg: DMTetStageConfig, target: ReferenceTarget, suite: PriorSuite, dmtet: DMTet,
                 texture: TextureField, device: torch.device, teacher: Silhouettes | None = None) -> None:
        self.cfg, self.dmtet, self.texture = cfg, dmtet, texture
        self.teacher = teacher if cfg.nerf_silhouette_weight > 0 else None
        super().__init__(target, suite, cfg.guidance, RenderSchedule.of(cfg), {"dmtet": dmtet, "texture": texture}, [
            {"params": [dmtet.sdf], "lr": cfg.lr_sdf},
            {"params": [dmtet.deform], "lr": cfg.lr_deform},
            {"params": list(texture.encoding.parameters()), "lr": cfg.lr_grid},
            {"params": list(texture.mlp.parameters()), "lr": cfg.lr_mlp},
        ], device, cfg.loop)

    def mesh(self) -> Mesh:
        try:
            return self.dmtet()
        except (EmptySurfaceError, NonFiniteFieldError) as exc:
            raise BadStep(str(exc)) from exc

    def render_step(self, step: int, generator: torch.Generator) -> RenderedStep:
        cfg, shape = self.cfg, self.shape(step)
        r = shape.resolution
        mesh = self.mesh()
        if mesh.num_faces == 0:
            raise BadStep("the DMTet surface is empty")
        cams = novel_cameras(shape.n_views, generator, self.device)
        ref, novel_out = render_mesh_groups(mesh, [self.target.camera, cams], r, r, self.texture)
        novel = novel_out.rgb_chw()
        m = mask_bce(ref.opacity_chw(), self.target_at(r).mask)
        lap, nc = laplacian_smoothness(mesh), normal_consistency(mesh)
        reg = self.dmtet.sdf_regulariser()
        loss = (cfg.mask_weight * m + cfg.laplacian_weight * lap + cfg.normal_consistency_weight * nc
                + cfg.sdf_reg_weight * reg)
        terms = {"mask_bce": m.detach(), "laplacian": lap.detach(), "normal_consistency": nc.detach(),
                 "sdf_reg": reg.detach()}
        if self.teacher is not None:
            view = step % len(self.teacher.cameras)  # a fixed cycle: the step's random draws stay as they were
            size = self.teacher.opacity.shape[-1]
            alpha = render_mesh(mesh, self.teacher.cameras[view:view + 1], size, size, _no_colour).opacity_chw()
            sil = mask_bce(alpha, self.teacher.opacity[view][None, None])
            loss = loss + cfg.nerf_silhouette_weight * sil
            terms["nerf_silhouette"] = sil.detach()
        return RenderedStep(cams, novel, ref.rgb_chw(), loss, terms)

    @torch.no_grad()
    def render_eval(self, cameras: Any, size: int | None = None) -> Any:
        r = size or self.cfg.resolution
        return render_mesh(self.mesh(), cameras, r, r, self.texture)

    def evaluate(self, done: int) -> dict[str, float]:
        try:
            return super().evaluate(done)
        except BadStep:
            return {"ref_psnr": float("nan")}


def _no_colour(points: torch.Tensor) -> torch.Tensor:
    return torch.zeros_like(points)


def init_from_nerf(dmtet: DMTet, texture: TextureField, nerf_dir: Path, cfg: DMTetStageConfig,
                   device: torch.device, generator: torch.Generator,
                   phase: Callable[[str], None] | None = None) -> tuple[float, Conversion]:
    """SDF from the NeRF at the iso-level its silhouettes choose (``nerf_to_dmtet``), texture field
    fitted to its albedo; returns the fit MSE and the conversion (level, silhouette IoUs).
    ``phase`` hears which of the two long calls starts (a ``Heartbeat``'s ``set_phase``)."""
    phase = phase or (lambda _: None)
    nerf, occupancy = load_nerf(nerf_dir, device)
    phase(f"converting NeRF → DMTet: {len(cfg.conversion.levels)} iso-levels on a {dmtet.config.resolution}³ grid")
    with torch.no_grad():
        conversion = convert(dmtet, nerf, cfg.conversion, occupancy)
        mesh = dmtet()
        pts = jittered_surface_points(mesh.vertices, cfg.colour_fit_points, 2 * dmtet.config.cell_size, generator)
        colours = torch.cat([nerf.query(p).albedo for p in pts.split(1 << 16)])
    phase(f"fitting the texture field to the NeRF's colours ({cfg.colour_fit_steps} steps)")
    return fit_colour_field(texture, pts, colours, cfg.colour_fit_steps, generator), conversion


def init_from_asset(dmtet: DMTet, texture: TextureField, asset: Path, cfg: DMTetStageConfig,
                    device: torch.device, generator: torch.Generator) -> float:
    """SDF sign from the asset's winding number (inside ≥ ½), texture fitted to its baked colours."""
    textured = load_textured(asset).to(device)
    shape = textured.mesh
    if shape.num_faces > cfg.init_mesh_max_faces:  # the winding number is O(points × faces)
        shape = cluster_decimate(shape, cfg.init_mesh_max_faces)
    extent = float(textured.vertices.abs().max())
    if extent > dmtet.config.half_extent:
        raise ValueError(f"{asset}: the mesh reaches {extent:.2f} but the grid spans ±{dmtet.config.half_extent}; "
                         "scale it into the unit cube (the pipeline's convention) before refining")
    with torch.no_grad():
        dmtet.init_from_density(lambda p: winding_number(shape, p), threshold=0.5)
    pts, colours = sample_surface(textured, cfg.colour_fit_points, generator)
    return fit_colour_field(texture, pts, colours, cfg.colour_fit_steps, generator)


def save_mesh(path: Path, mesh: Mesh) -> Path:
    """Vertices (float32) and faces (int64) as safetensors: reproducible bytes, no pickle."""
    from safetensors.torch import save_file

    tensors = {"vertices": mesh.vertices.detach().float().cpu().contiguous(),
               "faces": mesh.faces.detach().long().cpu().contiguous()}
    return atomic_write(path, lambda tmp: save_file(tensors, str(tmp)))


def load_mesh(path: Path, device: torch.device) -> Mesh:
    from safetensors.torch import load_file

    if not Path(path).is_file():
        raise FileNotFoundError(f"{path} is missing: run the dmtet stage first")
    data = load_file(str(path))
    return Mesh(data["vertices"].to(device), data["faces"].to(device))


def start_dmtet(reference_dir: Path, out_dir: Path, cfg: DMTetStageConfig, priors: PriorsConfig, object_id: str,
                nerf_dir: Path | None = None, init_mesh: Path | None = None, planned_grid: int | None = None,
                device: str = "auto", seed: int = 0, suite: PriorSuite | None = None,
                progress: ProgressFn | None = None) -> StageJob:
    """Stage 1b from the NeRF in ``nerf_dir`` or from an existing asset ``init_mesh``, set up to run
    (alone or in a batch). The set-up (minutes on a CPU: the conversion, the colour fit, loading
    the priors) reports through ``progress`` every ``HEARTBEAT_S`` s, as the loop does after it."""
    if (nerf_dir is None) == (init_mesh is None):
        raise ValueError("give exactly one of nerf_dir (the NeRF stage's output) or init_mesh (a GLB/OBJ)")
    dev = pick_device(device)
    generator = torch.Generator().manual_seed(seed + 1)
    torch.manual_seed(seed + 1)
    grid = choose_grid(cfg, planned_grid)
    dmtet = DMTet(DMTetConfig(resolution=grid, deform_scale=cfg.deform_scale), device=dev)
    texture = TextureField(cfg.texture_field, generator=generator).to(dev)
    with Heartbeat(progress, "dmtet", announce=True) as beat:
        if init_mesh is not None:
            beat.set_phase(f"initialising from {Path(init_mesh).name}: winding number, colour fit")
            fit_mse = init_from_asset(dmtet, texture, Path(init_mesh), cfg, dev, generator)
            notes = [f"initialised from {Path(init_mesh).name} (winding number) instead of a NeRF"]
            init_metrics = {}
            teacher = None
        else:
            fit_mse, conversion = init_from_nerf(dmtet, texture, Path(nerf_dir), cfg, dev, generator, beat.set_phase)
            notes = [f"NeRF → DMTet at occupancy level {conversion.level:g}: mean silhouette IoU "
                     f"{conversion.iou:.3f} against the NeRF over {len(conversion.silhouettes.opacity)} views"]
            init_metrics = {"iso_level": conversion.level, "init_silhouette_iou": round(conversion.iou, 4)}
            teacher = conversion.silhouettes
        target = ReferenceTarget.load(reference_dir, cfg.resolution, dev)
        if suite is None:
            beat.set_phase("loading the priors")
            suite = build_suite(priors, dev, reference_dir, object_id, cfg.guidance.roles, cfg.guidance.vsd_roles)
    try:
        task = DMTetTask(cfg, target, suite, dmtet, texture, dev, teacher)
    except BaseException:
        suite.close()
        raise

    def finish(result: LoopResult) -> StageResult:
        mesh = task.mesh()
        require_finite_output("dmtet", {"vertices": mesh.vertices, **dict(texture.state_dict())})
        save_mesh(out_dir / MESH_FILE, mesh)
        save_module(out_dir / TEXTURE_FILE, texture, cfg.texture_field)
        save_module(out_dir / DMTET_FILE, dmtet, DMTetConfig(resolution=grid, deform_scale=cfg.deform_scale))
        save_stage_preview(out_dir, reference_dir, task.render_eval, cfg.preview_size, dev)
        write_log(out_dir, result)
        metrics = loop_metrics(result) | {"grid": grid, "faces": mesh.num_faces, "vertices": mesh.num_vertices,
                                          "colour_fit_mse": round(fit_mse, 6), **init_metrics}
        if teacher is not None:  # how much of the NeRF's silhouettes the optimised mesh still holds
            alpha = mesh_silhouettes(dmtet, teacher, teacher.opacity.shape[-1])
            metrics["final_silhouette_iou"] = round(float(silhouette_iou(alpha, teacher.opacity).mean()), 4)
        return StageResult(metrics, suite.description, str(dev), notes)

    return StageJob("dmtet", task, generator, cfg.loop, finish, suite.close)


def _build(ctx: StageContext, cfg: DMTetStageConfig) -> StageWork:
    plan = ctx.plan
    grid = plan.dmtet_grid.value if plan is not None else None
    config = {"dmtet": cfg, "priors": ctx.priors, "prior_kind": ctx.prior_kind(cfg.guidance.roles),
              "seed": ctx.seed, "planned_grid": grid}
    inputs = {} if ctx.init_mesh is None else {"init_mesh": file_sha256(ctx.init_mesh)}

    def start(out: Path) -> StageJob:
        nerf_dir = None if ctx.init_mesh is not None else ctx.dir("nerf")
        return start_dmtet(ctx.dir("reference"), out, cfg, ctx.priors, ctx.key, nerf_dir, ctx.init_mesh, grid,
                           ctx.device, ctx.seed, ctx.suite("dmtet"), ctx.progress())

    return optimising(config, start, ctx, inputs)


MESH_NONEMPTY = CheckSpec("mesh_nonempty", ERROR, "the extracted mesh has faces")


def _judge(metrics: dict[str, Any], cfg: CheckThresholds) -> list[QACheck]:
    faces = int(metrics.get("faces", 0))
    return [check(MESH_NONEMPTY, faces > 0, faces, 1, f"{faces} faces"), *stable_optimisation(metrics, cfg)]


STAGE = Stage(
    "dmtet", CODE_VERSION, config=DMTetStageConfig, reads=("reference", "nerf"),
    writes=(MESH_FILE, TEXTURE_FILE, DMTET_FILE, PREVIEW_FILE, RUNLOG_FILE), preview=PREVIEW_FILE, gpu=True,
    build=_build, checks=(MESH_NONEMPTY, STABLE_OPTIMISATION), judge=_judge,
    description="Stage 1b: DMTet surface initialised from the NeRF density, mesh and texture field refined.")
