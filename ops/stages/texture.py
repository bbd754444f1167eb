"""Stage 2: refine the texture on the fixed DMTet geometry under the hybrid guidance.

The 3D prior guides every frequency with SDS (k3D = 1) and the 2D image-prompt prior guides only
the high frequencies (Λ keeps DCT indices ≥ r·D, r = 0.6) with VSD (k2D = 3, one LoRA per object,
lr 1e-4), plus the frequency-domain reference loss of each filter on the reference view. When
the plan found the object's texture flat (nothing above the high-pass band), the stage is a
recorded pass-through: the DMTet stage's texture field is kept and the reason is noted.
Output: ``texture_field.safetensors``, ``preview.png``, ``runlog.parquet``.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from morpheus_core.geometry.mesh import Mesh
from morpheus_core.guidance.presets import TEXTURE_GUIDANCE, GuidanceSettings
from morpheus_core.render.mesh_renderer import render_mesh, render_mesh_groups
from morpheus_core.runtime.devices import pick_device
from morpheus_core.texture import TextureField, TextureFieldConfig
from ops.engine.artifacts import RUNLOG_FILE, load_module, require_finite_output, save_module, write_log
from ops.engine.checks import STABLE_OPTIMISATION, stable_optimisation
from ops.engine.guided_task import GuidedTask, RenderedStep
from ops.engine.loop import LoopConfig, LoopResult
from ops.engine.previews import PREVIEW_FILE, save_stage_preview
from ops.engine.priors import PriorsConfig, PriorSuite, build_suite
from ops.engine.render_phases import Phase, RenderSchedule, check_phases
from ops.engine.stage import Stage, StageContext, StageWork, optimising
from ops.engine.stage_job import StageJob, StageResult, loop_metrics
from ops.engine.target import ReferenceTarget, novel_cameras
from ops.stages.dmtet import MESH_FILE as DMTET_MESH
from ops.stages.dmtet import TEXTURE_FILE, load_mesh

CODE_VERSION = "texture_refine-2"  # 2: the official loss balance (kept as existing stores hold it)


@dataclass(frozen=True)
class TextureStageConfig:
    """Stage 2: the texture field's refinement on the fixed DMTet mesh under the hybrid guidance."""

    loop: LoopConfig = field(default_factory=lambda: LoopConfig(5000, checkpoint_every=500, log_every=50))
    resolution: int = 512
    """Render size (px) of the reference and novel views each step (the paper: 512)."""
    n_views: int = 1
    """Random orbit views rendered for the priors each step, besides the reference view."""
    phases: tuple[Phase, ...] = ()
    """Coarse render phases before ``resolution`` and ``n_views`` (``ops.engine.render_phases``): each
    ``{until, resolution, n_views}`` holds while the step is below ``until`` × the stage's steps."""
    guidance: GuidanceSettings = field(default_factory=lambda: TEXTURE_GUIDANCE)
    """The paper's stage 2: 3D prior SDS full band + 2D prior VSD high-pass (r = 0.6, k2D = 3)."""
    lr_grid: float = 1e-2
    """Adam learning rate of the texture field's hash-grid tables."""
    lr_mlp: float = 1e-3
    """Adam learning rate of the texture field's MLP."""
    follow_plan: bool = True
    """Pass the DMTet texture through (recorded) when the plan skips high-pass refinement (flat textures)."""
    preview_size: int = 192
    """Tile size (px) of ``preview.png`` (photo | reference render | three orbit views)."""

    def __post_init__(self) -> None:
        if self.resolution < 8 or self.n_views < 1:
            raise ValueError("resolution must be ≥ 8 and n_views ≥ 1")
        check_phases(self.phases)


class TextureTask(GuidedTask):
    def __init__(self, cfg: TextureStageConfig, target: ReferenceTarget, suite: PriorSuite, mesh: Mesh,
                 texture: TextureField, device: torch.device) -> None:
        self.cfg, self.mesh, self.texture = cfg, mesh, texture
        super().__init__(target, suite, cfg.guidance, RenderSchedule.of(cfg), {"texture": texture}, [
            {"params": list(texture.encoding.parameters()), "lr": cfg.lr_grid},
            {"params": list(texture.mlp.parameters()), "lr": cfg.lr_mlp},
        ], device, cfg.loop)

    def render_step(self, step: int, generator: torch.Generator) -> RenderedStep:
        shape = self.shape(step)
        r = shape.resolution
        cams = novel_cameras(shape.n_views, generator, self.device)
        ref, novel_out = render_mesh_groups(self.mesh, [self.target.camera, cams], r, r, self.texture)
        novel = novel_out.rgb_chw()
        return RenderedStep(cams, novel, ref.rgb_chw(), novel.new_zeros(()))

    @torch.no_grad()
    def render_eval(self, cameras: Any, size: int | None = None) -> Any:
        r = size or self.cfg.resolution
        return render_mesh(self.mesh, cameras, r, r, self.texture)


def pass_through(dmtet_dir: Path, out_dir: Path, device: str, plan_reason: str) -> StageResult:
    """The recorded pass-through of a flat texture: the DMTet stage's texture field is kept."""
    shutil.copyfile(Path(dmtet_dir) / TEXTURE_FILE, out_dir / TEXTURE_FILE)
    shutil.copyfile(Path(dmtet_dir) / PREVIEW_FILE, out_dir / PREVIEW_FILE)
    return StageResult({"skipped": True, "steps_run": 0}, "none (pass-through)", str(pick_device(device)),
                       [f"pass-through: the plan skips high-pass refinement — {plan_reason}"])


def start_texture(reference_dir: Path, dmtet_dir: Path, out_dir: Path, cfg: TextureStageConfig,
                  priors: PriorsConfig, object_id: str, device: str = "auto", seed: int = 0,
                  suite: PriorSuite | None = None) -> StageJob:
    """Stage 2 on the DMTet stage's mesh and texture field, set up to run (alone or in a batch)."""
    dev = pick_device(device)
    generator = torch.Generator().manual_seed(seed + 2)
    torch.manual_seed(seed + 2)
    mesh = load_mesh(Path(dmtet_dir) / DMTET_MESH, dev)
    texture, tex_cfg, _ = load_module(Path(dmtet_dir) / TEXTURE_FILE, TextureField, TextureFieldConfig, dev)
    target = ReferenceTarget.load(reference_dir, cfg.resolution, dev)
    suite = suite or build_suite(priors, dev, reference_dir, object_id, cfg.guidance.roles, cfg.guidance.vsd_roles)
    try:
        task = TextureTask(cfg, target, suite, mesh, texture, dev)
        before = task.ref_psnr()
    except BaseException:
        suite.close()
        raise

    def finish(result: LoopResult) -> StageResult:
        require_finite_output("texture", dict(texture.state_dict()))
        save_module(out_dir / TEXTURE_FILE, texture, tex_cfg)
        save_stage_preview(out_dir, reference_dir, task.render_eval, cfg.preview_size, dev)
        write_log(out_dir, result)
        return StageResult(loop_metrics(result) | {"ref_psnr_before": before, "skipped": False},
                           suite.description, str(dev))

    return StageJob("texture", task, generator, cfg.loop, finish, suite.close)


def _build(ctx: StageContext, cfg: TextureStageConfig) -> StageWork:
    plan = ctx.plan
    refine = plan is None or plan.highpass_refinement.action != "skip"
    reason = "" if plan is None else plan.highpass_refinement.reason
    config = {"texture": cfg, "priors": ctx.priors, "seed": ctx.seed, "planned_refine": refine,
              "prior_kind": ctx.prior_kind(cfg.guidance.roles)}
    if cfg.follow_plan and not refine:
        return StageWork(config, lambda out, _ckpt: pass_through(ctx.dir("dmtet"), out, ctx.device, reason))

    def start(out: Path) -> StageJob:
        return start_texture(ctx.dir("reference"), ctx.dir("dmtet"), out, cfg, ctx.priors, ctx.key,
                             ctx.device, ctx.seed, ctx.suite("texture"))

    return optimising(config, start, ctx)


STAGE = Stage(
    "texture", CODE_VERSION, config=TextureStageConfig, reads=("reference", "dmtet"),
    writes=(TEXTURE_FILE, PREVIEW_FILE, RUNLOG_FILE),
    preview=PREVIEW_FILE, gpu=True, build=_build,
    checks=(STABLE_OPTIMISATION,), judge=stable_optimisation,
    description="Stage 2: texture refined with the 3D prior (full band) and the 2D prior's VSD on the high "
                "frequencies; a recorded pass-through when the plan finds the texture flat.")
