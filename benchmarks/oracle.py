"""Oracle priors: the proxy (render-target) prior aimed at a synthetic scene's ground truth.

The paper's two priors fail in opposite bands, and the oracle reproduces exactly those failures
with a known answer (DESIGN.md §3): the ``3d`` role sees the truth low-passed (Zero123: right
shape and colours, no fine detail), the ``2d`` role sees it with a tint and hue shift confined to
its low band (the image-prompt 2D prior: sharp detail, drifting colours). Every stage of the real
pipeline runs unchanged; only the suite of priors is swapped in through ``run_photo(suites=…)``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial

import torch
from torch import Tensor

from benchmarks.scenes import Scene
from morpheus_core.cameras import Cameras
from morpheus_core.guidance_presets import PRIOR_2D, PRIOR_3D
from morpheus_core.priors.proxy.prior import ColourDeviation, LowPass
from morpheus_core.render.textured import render_textured
from ops.config.presets import PipelineConfig
from ops.engine.priors import PriorSuite, ProxySuite

OPTIMISING_STAGES = ("nerf", "dmtet", "texture")


@dataclass(frozen=True)
class OracleConfig:
    """``low_pass``: what the 3D prior keeps (r = 0.6: the band the 2D high-pass adds back);
    ``deviation``: the 2D prior's low-band colour error."""

    low_pass: LowPass = field(default_factory=lambda: LowPass(0.6))
    deviation: ColourDeviation = field(default_factory=ColourDeviation)

    def describe(self) -> str:
        d = self.deviation
        return (f"3d: truth low-passed (r = {self.low_pass.r}); 2d: truth with hue +{d.hue_degrees}° and tint "
                f"{d.tint} below r = {d.r}")


def oracle_suite(scene: Scene, roles: tuple[str, ...], vsd_roles: tuple[str, ...], device: torch.device,
                 cfg: OracleConfig) -> ProxySuite:
    truth = scene.mesh.to(device)

    def target_images(cameras: Cameras, height: int, width: int) -> Tensor:
        with torch.no_grad():
            return render_textured(truth, cameras.to(device=device), height, width).rgb_chw().contiguous()

    corruptions = {PRIOR_3D: cfg.low_pass, PRIOR_2D: cfg.deviation}
    return ProxySuite(target_images, roles, vsd_roles, f"oracle of scene {scene.name} — {cfg.describe()}",
                      corruptions)


def oracle_suites(scene: Scene, pipeline: PipelineConfig, device: torch.device,
                  cfg: OracleConfig | None = None) -> dict[str, Callable[[], PriorSuite]]:
    """One suite factory per optimising stage, with that stage's roles (for ``run_photo``)."""
    cfg = cfg or OracleConfig()
    stage_cfgs = {"nerf": pipeline.nerf, "dmtet": pipeline.dmtet, "texture": pipeline.texture}
    return {stage: partial(oracle_suite, scene, c.guidance.roles, c.guidance.vsd_roles, device, cfg)
            for stage, c in stage_cfgs.items()}
