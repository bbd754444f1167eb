"""The one configuration object of a run, and its presets: ``paper``, ``fast``, ``standard``, ``draft``.

- ``paper``: the paper's schedule (DESIGN.md §3): NeRF 10k steps at 128 px with 256 samples per
  ray, DMTet 5k steps at 512 px on a grid up to 128, texture 5k steps at 512 px, 1024² texture.
- ``standard``: the same method at about a quarter of the cost (fewer steps, 96/256 px).
- ``fast``: the paper's method and resolutions for about a quarter of its GPU time: a quarter of its
  steps, the first half of each stage rendering several views per step at half size (coarse-to-fine
  render phases, ``ops.engine.render_phases``). Measured worse than ``paper``: at 1/20 of both schedules
  it loses 2.4–4.0 dB GLB PSNR on every benchmark scene (docs/performance.md).
- ``draft``: small enough for a 2-core CPU (one photo end to end in a few minutes): tiny
  renders, a small hash grid, short schedules. For previews, tests and the demo.

Everything is overridable by dotted path (``ops.engine.config_tree.apply_overrides``), e.g.
``--set texture.guidance.k2d=0`` (the paper's Base row) or ``--set nerf.loop.steps=2000``.

``execution`` (``morpheus_core.runtime.execution.ExecutionConfig``) is how the kernels run, not what they
compute: no stage's fingerprint holds it, and a run applies it process-wide when it starts
(``ops.pipeline.runner.run_setup``). Its defaults come from the environment aliases
(``MORPHEUS_HASHGRID``, ``MORPHEUS_FIELD_MLP``, ``MORPHEUS_COMPILE``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, make_dataclass, replace

from morpheus_core.export.uv_bake import BakeConfig
from morpheus_core.geometry.hashgrid import HashGridConfig
from morpheus_core.nerf_to_dmtet import ConversionConfig
from morpheus_core.render.volume import OccupancyGridConfig, VolumeRenderConfig
from morpheus_core.runtime.execution import ExecutionConfig
from morpheus_core.texture import TextureFieldConfig
from ops.config.preset_names import PRESET_NAMES
from ops.engine.config_tree import ConfigError, apply_overrides
from ops.engine.loop import LoopConfig
from ops.engine.priors import PriorsConfig
from ops.engine.render_phases import Phase
from ops.migrations import RENAMED_KEYS
from ops.stages import STAGES
from ops.stages.bake import BakeStageConfig
from ops.stages.dmtet import DMTetStageConfig
from ops.stages.nerf import NerfStageConfig, small_field
from ops.stages.qa import QAConfig
from ops.stages.texture import TextureStageConfig

log = logging.getLogger("morpheus3d")


def execution_defaults() -> ExecutionConfig:
    """The execution settings' defaults from their environment aliases; a bad value is a
    ``ConfigError`` naming the variable and the key, as a bad ``--set`` names its key."""
    try:
        return ExecutionConfig.from_env()
    except ValueError as exc:
        raise ConfigError(str(exc)) from exc


@dataclass(frozen=True)
class RunSettings:
    """What every stage of a run shares; ``PipelineConfig`` adds one section per declared stage."""

    seed: int = 0
    """Seed of the fitting stages' random numbers (field init, novel cameras, ray jitter, diffusion noise)."""
    device: str = "auto"
    """Torch device: ``auto`` (CUDA if available, else CPU; the learned QA metrics: CPU), ``cpu``, ``cuda:1``…"""
    priors: PriorsConfig = field(default_factory=PriorsConfig)
    execution: ExecutionConfig = field(default_factory=execution_defaults)
    """How the kernels run (Triton or eager, torch.compile): results differ by rounding only, so no stage's
    fingerprint holds it and changing it reuses cached outputs."""


# The run's configuration: ``RunSettings`` and, per stage in pipeline order, a section ``<id>`` of the stage's
# declared config class (``Stage.config``) with its defaults: a new stage needs no line here.
PipelineConfig = make_dataclass(
    "PipelineConfig", [(s.id, s.config, field(default_factory=s.config)) for s in STAGES],
    bases=(RunSettings,), frozen=True)
PipelineConfig.__module__ = __name__  # pickles and reprs name it here


def paper() -> PipelineConfig:
    return PipelineConfig()


def standard() -> PipelineConfig:
    return PipelineConfig(
        nerf=NerfStageConfig(loop=LoopConfig(3000, checkpoint_every=250, log_every=25), resolution=96,
                           render=VolumeRenderConfig(n_samples=128, with_normals=False)),
        dmtet=DMTetStageConfig(loop=LoopConfig(1500, checkpoint_every=250, log_every=25), resolution=256, max_grid=96),
        texture=TextureStageConfig(loop=LoopConfig(1500, checkpoint_every=250, log_every=25), resolution=256),
        qa=QAConfig(eval_resolution=512, turntable_views=36),
    )


def fast() -> PipelineConfig:
    """A quarter of the paper's steps (2500 + 1250 + 1250) at its resolutions. The first half of each
    stage renders at half size: four views per step in the NeRF stage (its renders are cheap per view),
    two in the mesh stages (their 2D prior runs per view). Early on the object is blurry and a prior's
    guess differs per noise draw and view, so more, smaller views buy more than sharp single ones
    (threestudio's Stable Zero123 recipe: 64 → 128 → 256 px with 12 → 8 → 4 views)."""
    base = paper()
    loops = {s: LoopConfig(getattr(base, s).loop.steps // 4, checkpoint_every=250, log_every=25)
             for s in ("nerf", "dmtet", "texture")}
    # The hash grid's levels switch on over the same share of the shorter schedule.
    grid = scaled_levels(base.nerf.model.grid, loops["nerf"].steps / base.nerf.loop.steps)
    return replace(
        base,
        nerf=replace(base.nerf, loop=loops["nerf"], model=replace(base.nerf.model, grid=grid),
                     phases=(Phase(0.5, base.nerf.resolution // 2, 4),)),
        dmtet=replace(base.dmtet, loop=loops["dmtet"], phases=(Phase(0.5, base.dmtet.resolution // 2, 2),)),
        texture=replace(base.texture, loop=loops["texture"], phases=(Phase(0.5, base.texture.resolution // 2, 2),)),
    )


def draft() -> PipelineConfig:
    small_texture = TextureFieldConfig(hashgrid=HashGridConfig(n_levels=8, log2_table_size=15, per_level_scale=1.6),
                                       hidden_dim=32)
    steps = 150
    return PipelineConfig(
        priors=PriorsConfig(proxy_grid=40),
        nerf=NerfStageConfig(loop=LoopConfig(steps, checkpoint_every=25, log_every=10), resolution=48,
                           model=small_field(), render=VolumeRenderConfig(n_samples=48, with_normals=False),
                           occupancy=OccupancyGridConfig(resolution=32, update_every=8),
                           preview_size=128,
                           normal_smooth_weight=0.0),  # normals cost 6 extra density queries per sample
        dmtet=DMTetStageConfig(loop=LoopConfig(80, checkpoint_every=20, log_every=10), resolution=96, max_grid=40,
                             texture_field=small_texture, colour_fit_steps=150, colour_fit_points=1 << 13,
                             preview_size=128, conversion=ConversionConfig(samples=48)),
        texture=TextureStageConfig(loop=LoopConfig(60, checkpoint_every=20, log_every=10), resolution=96,
                                    preview_size=128),
        bake=BakeStageConfig(map=BakeConfig(texture_size=256, padding=2, dilation_iterations=4), preview_size=128,
                          eval_resolution=128),
        # The part check renders the NeRF with the samples per ray it was fitted with.
        qa=QAConfig(eval_resolution=128, turntable_views=24, turntable_resolution=128, part_samples=48),
    )


PRESETS: dict[str, Callable[[], PipelineConfig]] = {"draft": draft, "standard": standard, "fast": fast,
                                                    "paper": paper}
if tuple(PRESETS) != PRESET_NAMES:
    raise ImportError(f"ops.config.presets defines {tuple(PRESETS)}, ops.config.preset_names names {PRESET_NAMES}")


def current_key(assignment: str) -> str:
    """``assignment`` (``key=value``) with a key from before the renaming spelled the current way."""
    for old, new in RENAMED_KEYS.items():
        if assignment.startswith(old):
            renamed = new + assignment[len(old):]
            log.warning("--set %s: the key is now %s", assignment.partition("=")[0], renamed.partition("=")[0])
            return renamed
    return assignment


def preset(name: str, overrides: Iterable[str] = ()) -> PipelineConfig:
    """The named preset with ``key=value`` overrides applied (``ConfigError`` names bad keys)."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}")
    return apply_overrides(PRESETS[name](), [current_key(o) for o in overrides])


def with_steps(cfg: PipelineConfig, nerf: int, dmtet: int, texture: int) -> PipelineConfig:
    """Shorter schedules with the same shape (tests, benchmarks): checkpoints, logs and the NeRF hash
    grid's progressive level schedule scale along (the paper's 16 levels are all on at 60 % of its
    10k steps; unscaled, a 1k-step run would fit 8 levels and switch the rest on untrained at its end)."""
    def loop(old: LoopConfig, steps: int) -> LoopConfig:
        every = max(1, steps // 4)
        return replace(old, steps=steps, checkpoint_every=every, log_every=max(1, steps // 8))

    grid = scaled_levels(cfg.nerf.model.grid, nerf / cfg.nerf.loop.steps)
    return replace(
        cfg,
        nerf=replace(cfg.nerf, loop=loop(cfg.nerf.loop, nerf), model=replace(cfg.nerf.model, grid=grid)),
        dmtet=replace(cfg.dmtet, loop=loop(cfg.dmtet.loop, dmtet)),
        texture=replace(cfg.texture, loop=loop(cfg.texture.loop, texture)),
    )


def scaled_levels(grid: HashGridConfig, factor: float) -> HashGridConfig:
    """``grid`` with its progressive level schedule stretched by ``factor`` (steps scale, levels do not)."""
    if not (factor > 0 and math.isfinite(factor)):
        raise ValueError(f"the schedule factor must be finite and > 0, got {factor}")
    return replace(grid, start_step=round(grid.start_step * factor),
                   update_steps=max(1, round(grid.update_steps * factor)))
