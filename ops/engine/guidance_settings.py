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
    """One stage's hybrid guidance (Algorithm 1): the 3D prior, the optional 2D prior, t schedule, λc, σ."""

    lambda_c: float = LAMBDA_C
    """λc in [0, 1]: prior terms weigh λc, the reference-view terms (1 − λc)/σ² (the paper: 5e-4)."""
    sigma: float = SIGMA
    """σ > 0 of the reference-view terms' weight (1 − λc)/σ² (the paper: 1)."""
    k3d: float = K_3D
    """Weight k ≥ 0 of the 3D prior (Zero123, full band) and its reference term (the paper: 1); 0 makes it inactive."""
    mode_3d: Mode = "sds"
    """``sds`` or ``vsd`` for the 3D prior (vsd trains a per-object LoRA; the paper's "fine-tuned 3D" ablation)."""
    cfg_3d: float = CFG_3D
    """Classifier-free guidance scale of the 3D prior's noise prediction (the paper: 3)."""
    t_lo: float = 0.02
    """Lower bound of the diffusion timestep t, as a fraction of T (the paper: 0.02)."""
    t_hi: float = 0.5
    """Upper bound of t as a fraction of T (the paper: 0.5); after the anneal when ``t_hi_start`` is set."""
    t_hi_start: float | None = None
    """Upper bound of t until ``anneal_step``, then ``t_hi`` (the paper's NeRF: 0.98 → 0.5); None: no anneal."""
    anneal_step: int | None = None
    """Step where t's upper bound drops to ``t_hi`` (paper: 5k of 10k); None: half the stage's steps."""
    use_2d: bool = False
    """Add the 2D prior (SD1.5 + canny ControlNet + IP-Adapter) term; false is the paper's Base row."""
    k2d: float = K_2D
    """Weight k ≥ 0 of the 2D prior's band and its reference term (the paper: 3; the k2D sweep: 0–5)."""
    r: float = HIGH_PASS_R
    """2D prior's high-pass cut: DCT indices ≥ r·D are kept (paper: 0.6); 0 = full band, 1 = none (term off)."""
    mode_2d: Mode = "vsd"
    """``vsd`` (a per-object LoRA counterpart, the paper) or ``sds`` for the 2D prior ("high-pass w/o fine-tuning")."""
    cfg_2d: float = CFG_2D
    """Classifier-free guidance scale of the 2D prior's noise prediction (the paper: 2)."""
    cfg_lora: float = CFG_LORA
    """Classifier-free guidance scale of the VSD LoRA counterpart's prediction ε_φ (1: no guidance)."""
    grad_clip: float | None = None
    """Clamp each element of the prior gradient to ±this; None: no clamp."""

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
