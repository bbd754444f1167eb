"""Stage 1a: fit a hash-grid NeRF to the photo under the 3D prior (SDS, t annealed).

Each step renders the reference view and ``n_views`` random orbit views. The reference view gets
the reference guidance of Algorithm 1 (‖x0 − y‖², weighted (1 − λc)/σ²) and a mask BCE on its
opacity; the random views get the 3D prior's guidance; an optional smoothness term on the
rendered normals of the random views tames floaters. Output: ``nerf.safetensors`` (field + occupancy
grid), ``preview.png`` (photo | reference render | novel views), ``runlog.parquet``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from morpheus_core.geometry.hashgrid import HashGridConfig
from morpheus_core.geometry.nerf import NerfConfig, NerfField
from morpheus_core.guidance.loss_balance import mask_bce
from morpheus_core.guidance.presets import NERF_GUIDANCE, GuidanceSettings
from morpheus_core.render.sample_budget import SampleBudget
from morpheus_core.render.volume import OccupancyGrid, OccupancyGridConfig, VolumeRenderConfig, render_volume
from morpheus_core.runtime.devices import pick_device
from ops.engine.artifacts import RUNLOG_FILE, load_module, require_finite_output, save_module, write_log
from ops.engine.checks import STABLE_OPTIMISATION, stable_optimisation
from ops.engine.guided_task import GuidedTask, RenderedStep
from ops.engine.loop import LoopConfig, LoopResult
from ops.engine.previews import PREVIEW_FILE, save_stage_preview
from ops.engine.priors import PriorsConfig, PriorSuite, build_suite
from ops.engine.render_phases import Phase, RenderSchedule, StepShape, check_phases
from ops.engine.stage import Stage, StageContext, StageWork, optimising
from ops.engine.stage_job import StageJob, StageResult, loop_metrics
from ops.engine.target import ReferenceTarget, novel_cameras

NERF_FILE = "nerf.safetensors"
CODE_VERSION = "nerf_fit-2"  # 2: the official loss balance (a version string, kept as existing stores hold it)


@dataclass(frozen=True)
class NerfStageConfig:
    loop: LoopConfig = field(default_factory=lambda: LoopConfig(steps=10_000, checkpoint_every=500, log_every=50))
    resolution: int = 128
    """Render size (px) of the reference and novel views each step (the paper: 128)."""
    n_views: int = 1
    """Random orbit views rendered for the 3D prior each step, besides the reference view."""
    phases: tuple[Phase, ...] = ()
    """Coarse render phases before ``resolution`` and ``n_views`` (``ops.engine.render_phases``): each
    ``{until, resolution, n_views}`` holds while the step is below ``until`` × the stage's steps."""
    model: NerfConfig = field(default_factory=NerfConfig)
    render: VolumeRenderConfig = field(default_factory=lambda: VolumeRenderConfig(n_samples=256, with_normals=False))
    occupancy: OccupancyGridConfig = field(default_factory=OccupancyGridConfig)
    use_occupancy: bool = True
    """Skip samples in empty occupancy-grid cells (``occupancy``); false evaluates the field at every sample."""
    guidance: GuidanceSettings = field(default_factory=lambda: NERF_GUIDANCE)
    """The paper's stage 1a: 3D prior SDS, t's upper bound annealed 0.98 → 0.5 halfway."""
    lr_grid: float = 1e-2
    """Adam learning rate of the hash-grid tables."""
    lr_mlp: float = 1e-3
    """Adam learning rate of the density and albedo MLPs."""
    mask_weight: float = 1.0
    """Weight of the reference view's opacity-vs-mask BCE (a mean over pixels, as the official code)."""
    normal_smooth_weight: float = 1.0
    """The official λ_normal_smoothness, on the mean over the novel views' normals; 0 skips rendering normals."""
    preview_size: int = 160
    """Tile size (px) of ``preview.png`` (photo | reference render | three orbit views)."""

    def __post_init__(self) -> None:
        if self.resolution < 8 or self.n_views < 1:
            raise ValueError("resolution must be ≥ 8 and n_views ≥ 1")
        check_phases(self.phases)


def normal_smoothness(normal: Tensor, opacity: Tensor) -> Tensor:
    """Squared differences of neighbouring rendered normals where both pixels are opaque, averaged
    over the elements (views × pixels × 3) of each direction like the official code's regulariser."""
    w = opacity.squeeze(-1)
    dx = (normal[:, :, 1:] - normal[:, :, :-1]).pow(2) * (w[:, :, 1:] * w[:, :, :-1]).unsqueeze(-1)
    dy = (normal[:, 1:] - normal[:, :-1]).pow(2) * (w[:, 1:] * w[:, :-1]).unsqueeze(-1)
    return dx.mean() + dy.mean()


class NerfTask(GuidedTask):
    def __init__(self, cfg: NerfStageConfig, target: ReferenceTarget, suite: PriorSuite, device: torch.device,
                 generator: torch.Generator) -> None:
        self.cfg = cfg
        self.field = NerfField(cfg.model, generator=generator).to(device)
        self.occupancy = OccupancyGrid(cfg.occupancy, cfg.model.bbox_radius).to(device)
        modules = {"field": self.field, "occupancy": self.occupancy}
        super().__init__(target, suite, cfg.guidance, RenderSchedule.of(cfg), modules, [
            {"params": list(self.field.encoding.parameters()), "lr": cfg.lr_grid},
            {"params": list(self.field.density_mlp.parameters()) + list(self.field.albedo_mlp.parameters()),
             "lr": cfg.lr_mlp},
        ], device, cfg.loop)
        # Every render setting of the config reaches both renders; only what a render is for differs.
        self.eval_render = replace(cfg.render, stratified=False, with_normals=False)
        cfg.render.sample_buffer_on(device)  # a buffer this device cannot have fails here, not at the first step
        self.budget: SampleBudget | None = None
        self._buffer: str | None = None  # resolved at the first step: a batch says by then that it holds this task
        self.samples_dropped = 0

    def _render(self, cameras: Any, generator: torch.Generator, with_normals: bool, key: str,
                shape: StepShape) -> Any:
        render_cfg = replace(self.cfg.render, stratified=True, with_normals=with_normals)
        occ = self.occupancy if self.cfg.use_occupancy else None
        r = shape.resolution
        # One sample buffer per render and phase: a phase's ray count sizes its own buffer (and graph).
        return render_volume(self.field, cameras, r, r, render_cfg, 1.0, occ, generator, self.budget,
                             key if shape.final else f"{key}/phase{shape.index}")

    def _resolve_buffer(self) -> None:
        if self._buffer is None:
            self._buffer = self.cfg.render.sample_buffer_on(self.device, alone=self.shared_by == 1)
            self.budget = SampleBudget(graphed=self._buffer == "graphed") if self._buffer != "exact" else None

    def _prepare(self, step: int, generator: torch.Generator) -> None:
        self._resolve_buffer()
        self.field.update_step(step)
        if self.cfg.use_occupancy and self.occupancy.maybe_refresh(self.field, step, generator) \
                and self.budget is not None:
            self.samples_dropped += sum(self.budget.adapt().values())  # the grid changed: resize the buffers

    def _step_losses(self, ref: Any, cams: Any, novel: Any, shape: StepShape) -> RenderedStep:
        cfg = self.cfg
        m = mask_bce(ref.opacity_chw(), self.target_at(shape.resolution).mask)
        loss, terms = cfg.mask_weight * m, {"mask_bce": m.detach()}
        if cfg.normal_smooth_weight > 0:
            s = normal_smoothness(novel.normal, novel.opacity)
            loss = loss + cfg.normal_smooth_weight * s
            terms["normal_smooth"] = s.detach()
        if self.budget is not None:  # samples past a full buffer, since the stage began
            terms["samples_dropped"] = self.budget.dropped() + self.samples_dropped  # type: ignore[operator]
        return RenderedStep(cams, novel.rgb_chw(), ref.rgb_chw(), loss, terms)

    def render_step(self, step: int, generator: torch.Generator) -> RenderedStep:
        self._prepare(step, generator)
        shape = self.shape(step)
        ref = self._render(self.target.camera, generator, False, "reference", shape)
        cams = novel_cameras(shape.n_views, generator, self.device)
        novel = self._render(cams, generator, self.cfg.normal_smooth_weight > 0, "novel", shape)
        return self._step_losses(ref, cams, novel, shape)

    def last_phase(self, step: int) -> bool:
        # Finer hash-grid levels still switching on: stopping now would leave them untrained.
        return super().last_phase(step) and self.cfg.model.grid.levels_at(step) >= self.cfg.model.grid.n_levels

    @torch.no_grad()
    def render_eval(self, cameras: Any, size: int | None = None) -> Any:
        occ = self.occupancy if self.cfg.use_occupancy else None
        r = size or self.cfg.resolution
        return render_volume(self.field, cameras, r, r, self.eval_render, 1.0, occ)


def start_nerf(reference_dir: Path, out_dir: Path, cfg: NerfStageConfig, priors: PriorsConfig, object_id: str,
               device: str = "auto", seed: int = 0, suite: PriorSuite | None = None) -> StageJob:
    """Stage 1a for a prepared reference folder, set up to run (alone or in a batch); writes into
    ``out_dir`` when it finishes."""
    dev = pick_device(device)
    generator = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    target = ReferenceTarget.load(reference_dir, cfg.resolution, dev)
    suite = suite or build_suite(priors, dev, reference_dir, object_id, cfg.guidance.roles, cfg.guidance.vsd_roles)
    try:
        task = NerfTask(cfg, target, suite, dev, generator)
    except BaseException:
        suite.close()
        raise

    def finish(result: LoopResult) -> StageResult:
        task.field.update_step(cfg.loop.steps)
        require_finite_output("nerf", dict(task.field.state_dict()))
        save_module(out_dir / NERF_FILE, task.field, cfg.model, {"occupancy": task.occupancy.density})
        save_stage_preview(out_dir, reference_dir, task.render_eval, cfg.preview_size, dev)
        write_log(out_dir, result)
        metrics = loop_metrics(result) | {"ref_psnr": task.ref_psnr(),
                                          "occupied_fraction": round(task.occupancy.occupied_fraction, 4)}
        if task.budget is not None:  # under ``graphed``, each resize captured the buffer's graph again
            metrics["sample_buffer_resizes"] = task.budget.resizes
        return StageResult(metrics, suite.description, str(dev))

    return StageJob("nerf", task, generator, cfg.loop, finish, suite.close)



def load_nerf(nerf_dir: Path, device: torch.device) -> tuple[NerfField, OccupancyGrid | None]:
    """The fitted field with every hash-grid level active (as at the end of stage 1a) and
    its saved occupancy grid, which skips empty space exactly as the fit's own renders did."""
    nerf, _, extra = load_module(Path(nerf_dir) / NERF_FILE, NerfField, NerfConfig, device)
    nerf.update_step(1 << 30)
    nerf.eval()
    density = extra.get("occupancy")
    if density is None or density.dim() != 3:
        return nerf, None
    grid = OccupancyGrid(OccupancyGridConfig(resolution=int(density.shape[0])), nerf.bbox_radius).to(device)
    grid.density.copy_(density.to(device))
    return nerf, grid


def small_field(levels: int = 8, log2_table: int = 15, hidden: int = 32) -> NerfConfig:
    """A NeRF field for CPU presets: fewer levels, a smaller table, narrower MLPs."""
    grid = HashGridConfig(n_levels=levels, log2_table_size=log2_table, per_level_scale=1.6,
                          start_levels=max(1, levels // 2), start_step=0, update_steps=25)
    return NerfConfig(grid=grid, hidden=hidden)


def _build(ctx: StageContext, cfg: NerfStageConfig) -> StageWork:
    config = {"nerf": cfg, "priors": ctx.priors, "prior_kind": ctx.prior_kind(cfg.guidance.roles), "seed": ctx.seed}

    def start(out: Path) -> StageJob:
        return start_nerf(ctx.dir("reference"), out, cfg, ctx.priors, ctx.key, ctx.device, ctx.seed,
                          ctx.suite("nerf"))

    return optimising(config, start, ctx)


STAGE = Stage(
    "nerf", CODE_VERSION, config=NerfStageConfig, reads=("reference",),
    writes=(NERF_FILE, PREVIEW_FILE, RUNLOG_FILE), preview=PREVIEW_FILE,
    gpu=True, build=_build, replaced_by_init_mesh=True,
    checks=(STABLE_OPTIMISATION,), judge=stable_optimisation,
    description="Stage 1a: hash-grid NeRF fitted to the reference under the 3D prior (SDS, t annealed 0.98 → 0.5).")
