"""The guidance knobs of a stage as flat, overridable settings; ``build()`` gives Algorithm 1's config.

Every row of the paper's ablations is a setting here (no code edits): Base is ``use_2d=false`` or
``k2d=0``, the full-pass 2D prior ``r=0``, high-pass without fine-tuning ``mode_2d=sds``, the
fine-tuned 3D prior ``mode_3d=vsd``, and the k2D / r sweeps set ``k2d`` / ``r``.
"""

from __future__ import annotations

from dataclasses import dataclass

from morpheus_core.diffusion import TimestepRange
from morpheus_core.guidance import GuidanceConfig, Mode
from morpheus_core.guidance_presets import (
    CFG_2D,
    CFG_3D,
    CFG_LORA,
    HIGH_PASS_R,
    K_2D,
    K_3D,
    LAMBDA_C,
    PRIOR_2D,
    PRIOR_3D,
    SIGMA,
    term_2d,
    term_3d,
)


@dataclass(frozen=True)
class GuidanceSettings:
    """t ∈ [t_lo, t_hi]; with ``t_hi_start`` set, the upper bound starts there and drops to
    ``t_hi`` at ``anneal_step`` (the paper: 0.98 → 0.5 at step 5k of the 10k NeRF stage). Unset,
    ``anneal_step`` is half of the stage's steps, so ``--set nerf.loop.steps=N`` anneals at N/2."""

    lambda_c: float = LAMBDA_C
    sigma: float = SIGMA
    k3d: float = K_3D
    mode_3d: Mode = "sds"
    cfg_3d: float = CFG_3D
    t_lo: float = 0.02
    t_hi: float = 0.5
    t_hi_start: float | None = None
    anneal_step: int | None = None
    use_2d: bool = False
    k2d: float = K_2D
    r: float = HIGH_PASS_R
    mode_2d: Mode = "vsd"
    cfg_2d: float = CFG_2D
    cfg_lora: float = CFG_LORA
    grad_clip: float | None = None

    def __post_init__(self) -> None:
        if self.mode_3d not in ("sds", "vsd") or self.mode_2d not in ("sds", "vsd"):
            raise ValueError("mode_3d and mode_2d must be 'sds' or 'vsd'")
        if not 0.0 <= self.r <= 1.0:
            raise ValueError(f"r must lie in [0, 1], got {self.r}")
        if self.anneal_step is not None and self.anneal_step < 0:
            raise ValueError(f"anneal_step must be ≥ 0 when set, got {self.anneal_step}")
        self.build(steps=2)  # validates every value now, not at the first step

    def t_range(self, steps: int) -> TimestepRange:
        """The t range of a stage of ``steps`` steps."""
        if self.t_hi_start is None:
            return TimestepRange(self.t_lo, self.t_hi)
        anneal = self.anneal_step if self.anneal_step is not None else max(1, steps // 2)
        start = max(anneal - 1, 0)
        return TimestepRange(self.t_lo, self.t_hi_start, hi_end=self.t_hi, anneal_start=start,
                             anneal_end=max(anneal, start))

    @property
    def roles(self) -> tuple[str, ...]:
        return (PRIOR_3D, PRIOR_2D) if self.use_2d else (PRIOR_3D,)

    @property
    def vsd_roles(self) -> tuple[str, ...]:
        modes = {PRIOR_3D: self.mode_3d, PRIOR_2D: self.mode_2d}
        return tuple(role for role in self.roles if modes[role] == "vsd" and self.is_active(role))

    def is_active(self, role: str) -> bool:
        return (self.k3d > 0) if role == PRIOR_3D else (self.use_2d and self.k2d > 0 and self.r < 1.0)

    def build(self, steps: int) -> GuidanceConfig:
        """Algorithm 1's config for a stage of ``steps`` steps (the schedule of t depends on them)."""
        # An inactive term (k = 0, or r = 1 for the 2D prior) adds exactly nothing, and ``vsd_roles``
        # gives it no LoRA: the 2D term is left out (no wasted prior forward); the 3D term stays so
        # the config is never empty, in SDS mode when inactive (VSD would ask for a missing LoRA).
        mode_3d = self.mode_3d if self.is_active(PRIOR_3D) else "sds"
        terms = [term_3d(mode_3d, self.k3d, self.t_range(steps), self.cfg_3d, self.cfg_lora)]
        if self.is_active(PRIOR_2D):
            terms.append(term_2d(self.mode_2d, self.k2d, self.r, self.t_range(steps), self.cfg_2d, self.cfg_lora))
        return GuidanceConfig(tuple(terms), self.lambda_c, self.sigma, self.grad_clip)
