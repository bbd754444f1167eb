"""Oracle priors: the proxy (render-target) prior aimed at a synthetic scene's ground truth.

The paper's two priors fail in opposite bands, and the oracle reproduces exactly those failures
with a known answer (DESIGN.md §3): the ``3d`` role sees the truth low-passed (Zero123: right
shape and colours, no fine detail), the ``2d`` role sees it with a tint and hue shift confined to
its low band (the image-prompt 2D prior: sharp detail, drifting colours). By default (``stochastic``)
each prediction also errs the way a real denoiser's does (``DenoiserError``): an error drawn from the
step's noise, growing with t and spatially correlated, a colour drift that changes from call to call
for the 2D role, a CFG that extrapolates from an unconditional branch, and a VSD counterpart that
shares part of the error. ``noise-free`` (the oracle before, a deterministic pull) stays for
regression tests and comparisons. Every stage of the real pipeline runs unchanged; only the suite of
priors is swapped in through ``Pipeline(suites=…)``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial

import torch
from torch import Tensor

from benchmarks.scenes import Scene
from morpheus_core.cameras import Cameras
from morpheus_core.guidance.presets import PRIOR_2D, PRIOR_3D
from morpheus_core.priors.proxy.denoiser_error import DenoiserError
from morpheus_core.priors.proxy.prior import ColourDeviation, LowPass
from morpheus_core.render.textured import render_textured
from ops.config.presets import PipelineConfig
from ops.engine.priors import PriorSuite, ProxySuite

OPTIMISING_STAGES = ("nerf", "dmtet", "texture")


ORACLE_KINDS = ("stochastic", "noise-free")

# The 2D role's per-call colour drift: half the systematic deviation's size (hue 30°, tint 0.06),
# so the model's colours vary around its bias rather than swamp it.
_DRIFT_2D = DenoiserError(drift_hue_sd=15.0, drift_tint_sd=0.03)


@dataclass(frozen=True)
class OracleConfig:
    """``low_pass``: what the 3D prior keeps (r = 0.6: the band the 2D high-pass adds back);
    ``deviation``: the 2D prior's systematic low-band colour error; ``error_3d`` / ``error_2d``: how
    each role's prediction errs like a real denoiser (None: noise-free)."""

    low_pass: LowPass = field(default_factory=lambda: LowPass(0.6))
    deviation: ColourDeviation = field(default_factory=ColourDeviation)
    error_3d: DenoiserError | None = field(default_factory=DenoiserError)
    error_2d: DenoiserError | None = _DRIFT_2D

    @staticmethod
    def named(kind: str) -> OracleConfig:
        """``stochastic`` (the benchmark's default) or ``noise-free`` (deterministic pull)."""
        if kind not in ORACLE_KINDS:
            raise ValueError(f"unknown oracle {kind!r}; choose one of {', '.join(ORACLE_KINDS)}")
        return OracleConfig() if kind == "stochastic" else OracleConfig(error_3d=None, error_2d=None)

    @property
    def kind(self) -> str:
        return "noise-free" if self.error_3d is None and self.error_2d is None else "stochastic"

    def describe(self) -> str:
        d = self.deviation
        text = (f"3d: truth low-passed (r = {self.low_pass.r}); 2d: truth with hue +{d.hue_degrees}° and tint "
                f"{d.tint} below r = {d.r}")
        for role, error in (("3d", self.error_3d), ("2d", self.error_2d)):
            text += f"; {role} {error.describe()}" if error is not None else f"; {role} noise-free"
        return text

    def errors(self) -> dict[str, DenoiserError]:
        return {role: e for role, e in ((PRIOR_3D, self.error_3d), (PRIOR_2D, self.error_2d)) if e is not None}


def oracle_suite(scene: Scene, roles: tuple[str, ...], vsd_roles: tuple[str, ...], device: torch.device,
                 cfg: OracleConfig) -> ProxySuite:
    truth = scene.mesh.to(device)

    def target_images(cameras: Cameras, height: int, width: int) -> Tensor:
        with torch.no_grad():
            return render_textured(truth, cameras.to(device=device), height, width).rgb_chw().contiguous()

    corruptions = {PRIOR_3D: cfg.low_pass, PRIOR_2D: cfg.deviation}
    return ProxySuite(target_images, roles, vsd_roles, f"{cfg.kind} oracle of scene {scene.name} — {cfg.describe()}",
                      corruptions, cfg.errors())


def oracle_suites(scene: Scene, pipeline: PipelineConfig, device: torch.device,
                  cfg: OracleConfig | None = None) -> dict[str, Callable[[], PriorSuite]]:
    """One suite factory per optimising stage, with that stage's roles (``Pipeline(suites=…)``)."""
    cfg = cfg or OracleConfig()
    stage_cfgs = {"nerf": pipeline.nerf, "dmtet": pipeline.dmtet, "texture": pipeline.texture}
    return {stage: partial(oracle_suite, scene, c.guidance.roles, c.guidance.vsd_roles, device, cfg)
            for stage, c in stage_cfgs.items()}
