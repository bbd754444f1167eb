"""Hybrid guidance as the stages configure it: the paper's numbers, the flat ``GuidanceSettings`` every
optimising stage exposes (``--set <stage>.guidance.…``; ``build()`` gives Algorithm 1's
``GuidanceConfig``), each stage's defaults, and every row of the paper's ablations as settings.

Prior names are roles: ``"3d"`` (Zero123, or a proxy in its place) and ``"2d"`` (the
image-prompt 2D prior). Numbers are the paper's (section 5.1 and the appendix). Every ablation row
is a setting (no code edits): Base is ``use_2d=false`` or ``k2d=0``, the full-pass 2D prior
``r=0``, high-pass without fine-tuning ``mode_2d=sds``, the fine-tuned 3D prior ``mode_3d=vsd``,
and the k2D / r sweeps set ``k2d`` / ``r``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from morpheus_core.guidance.diffusion import TimestepRange
from morpheus_core.guidance.frequency import BandMask
from morpheus_core.guidance.hybrid import BandWeight, GuidanceConfig, Mode, PriorTerm

PRIOR_3D = "3d"
PRIOR_2D = "2d"
LAMBDA_C = 5e-4
SIGMA = 1.0
CFG_3D = 3.0
CFG_2D = 2.0
CFG_LORA = 1.0
K_3D = 1.0
K_2D = 3.0
HIGH_PASS_R = 0.6
LATE_T = TimestepRange(0.02, 0.50)


def _band(r: float) -> BandMask:
    # r = 0 keeps every frequency and r = 1 none; name those cases so logs read naturally.
    if r <= 0.0:
        return BandMask.full()
    if r >= 1.0:
        return BandMask.null()
    return BandMask.high_pass(r)


def term_3d(mode: Mode = "sds", k: float = K_3D, t_range: TimestepRange = LATE_T, cfg_scale: float = CFG_3D,
            lora_cfg_scale: float = CFG_LORA) -> PriorTerm:
    return PriorTerm(
        PRIOR_3D, mode, (BandWeight(BandMask.full(), k),), cfg_scale=cfg_scale,
        finetuned_cfg_scale=lora_cfg_scale, t_range=t_range,
    )


def term_2d(mode: Mode = "vsd", k: float = K_2D, r: float = HIGH_PASS_R, t_range: TimestepRange = LATE_T,
            cfg_scale: float = CFG_2D, lora_cfg_scale: float = CFG_LORA) -> PriorTerm:
    return PriorTerm(
        PRIOR_2D, mode, (BandWeight(_band(r), k),), cfg_scale=cfg_scale,
        finetuned_cfg_scale=lora_cfg_scale, t_range=t_range,
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

    def build(self, steps: int, keep_inactive: bool = False) -> GuidanceConfig:
        """Algorithm 1's config for a stage of ``steps`` steps (the schedule of t depends on them).
        ``keep_inactive`` keeps a 2D term that adds nothing, as the paper's tables write such rows."""
        # An inactive term (k = 0, or r = 1 for the 2D prior) adds exactly nothing, and ``vsd_roles``
        # gives it no LoRA: the 2D term is left out (no wasted prior forward); the 3D term stays so
        # the config is never empty, in SDS mode when inactive (VSD would ask for a missing LoRA).
        mode_3d = self.mode_3d if self.is_active(PRIOR_3D) else "sds"
        terms = [term_3d(mode_3d, self.k3d, self.t_range(steps), self.cfg_3d, self.cfg_lora)]
        if self.is_active(PRIOR_2D) or (keep_inactive and self.use_2d):
            terms.append(term_2d(self.mode_2d, self.k2d, self.r, self.t_range(steps), self.cfg_2d, self.cfg_lora))
        return GuidanceConfig(tuple(terms), self.lambda_c, self.sigma, self.grad_clip)


# Each stage's guidance (DESIGN.md §3): NeRF with t annealed 0.98 → 0.5 half-way, DMTet with t in
# [0.02, 0.5], texture with both priors (3D SDS full band + 2D VSD high-pass r = 0.6, k2D = 3).
NERF_GUIDANCE = GuidanceSettings(t_hi_start=0.98, t_hi=0.5)
DMTET_GUIDANCE = GuidanceSettings()
TEXTURE_GUIDANCE = GuidanceSettings(use_2d=True)

# The paper's stage-2 ablation rows as changes to the texture stage's settings.
PAPER_ROWS: dict[str, dict[str, Any]] = {
    "base": {"use_2d": False},
    "full_pass_2d": {"r": 0.0},
    "high_pass_2d_sds": {"mode_2d": "sds"},
    "ours": {},
    "finetuned_3d": {"mode_3d": "vsd"},
    **{f"k2d={k}": {"k2d": float(k)} for k in (0, 1, 2, 3, 4, 5)},
    **{f"r={r:.1f}": {"r": r} for r in (0.0, 0.2, 0.4, 0.6, 0.8, 1.0)},
}


def nerf_t_range(anneal_step: int = 5000) -> TimestepRange:
    """[0.02, 0.98] for the first ``anneal_step`` steps, then [0.02, 0.50]."""
    return replace(NERF_GUIDANCE, anneal_step=anneal_step).t_range(2 * anneal_step)


def stage1_dmtet() -> GuidanceConfig:
    """Stage 1b: full-pass 3D prior with SDS, t ∈ [0.02, 0.5]."""
    return DMTET_GUIDANCE.build(steps=2)


def stage2_texture(
    k2d: float = K_2D, r: float = HIGH_PASS_R, mode_2d: Mode = "vsd", mode_3d: Mode = "sds"
) -> GuidanceConfig:
    """Stage 2 (Morpheus3D): 3D prior SDS full-pass + 2D prior VSD high-pass r = 0.6, k2D = 3."""
    settings = replace(TEXTURE_GUIDANCE, k2d=k2d, r=r, mode_2d=mode_2d, mode_3d=mode_3d)
    return settings.build(steps=2, keep_inactive=True)


def vsd(prior: str = PRIOR_3D, cfg_scale: float = CFG_3D) -> GuidanceConfig:
    """ProlificDreamer's VSD extended to image-to-3D: N = 1, M = 1, Λ = I."""
    term = PriorTerm(prior, "vsd", (BandWeight(BandMask.full(), 1.0),), cfg_scale=cfg_scale, t_range=LATE_T)
    return GuidanceConfig((term,), LAMBDA_C, SIGMA)


def magic123(k3d: float = 1.0, k2d: float = 1.0) -> GuidanceConfig:
    """Magic123: N = 2 priors, SDS, Λ = I."""
    return GuidanceConfig((term_3d("sds", k3d), term_2d("sds", k2d, 0.0)), LAMBDA_C, SIGMA)


def paper_ablations() -> dict[str, GuidanceConfig]:
    """Every stage-2 row of the paper's ablations, keyed by a short name (zero-weight terms kept)."""
    return {name: replace(TEXTURE_GUIDANCE, **change).build(steps=2, keep_inactive=True)
            for name, change in PAPER_ROWS.items()}
