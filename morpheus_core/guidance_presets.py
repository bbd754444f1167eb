"""The paper's guidance settings and every ablation row, as ``GuidanceConfig`` values.

Prior names are roles: ``"3d"`` (Zero123, or a proxy in its place) and ``"2d"`` (the
image-prompt 2D prior). Numbers are the paper's (section 5.1 and the appendix).
"""

from __future__ import annotations

from morpheus_core.diffusion import TimestepRange
from morpheus_core.frequency import BandMask
from morpheus_core.guidance import BandWeight, GuidanceConfig, Mode, PriorTerm

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


def nerf_t_range(anneal_step: int = 5000) -> TimestepRange:
    """[0.02, 0.98] for the first ``anneal_step`` steps, then [0.02, 0.50]."""
    return TimestepRange(0.02, 0.98, hi_end=0.50, anneal_start=anneal_step - 1, anneal_end=anneal_step)


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


def stage1_nerf(anneal_step: int = 5000) -> GuidanceConfig:
    """Stage 1a: full-pass 3D prior with SDS, t annealed."""
    return GuidanceConfig((term_3d(t_range=nerf_t_range(anneal_step)),), LAMBDA_C, SIGMA)


def stage1_dmtet() -> GuidanceConfig:
    """Stage 1b: full-pass 3D prior with SDS, t ∈ [0.02, 0.5]."""
    return GuidanceConfig((term_3d(),), LAMBDA_C, SIGMA)


def stage2_texture(
    k2d: float = K_2D, r: float = HIGH_PASS_R, mode_2d: Mode = "vsd", mode_3d: Mode = "sds"
) -> GuidanceConfig:
    """Stage 2 (Morpheus3D): 3D prior SDS full-pass + 2D prior VSD high-pass r = 0.6, k2D = 3."""
    return GuidanceConfig((term_3d(mode_3d), term_2d(mode_2d, k2d, r)), LAMBDA_C, SIGMA)


def vsd(prior: str = PRIOR_3D, cfg_scale: float = CFG_3D) -> GuidanceConfig:
    """ProlificDreamer's VSD extended to image-to-3D: N = 1, M = 1, Λ = I."""
    term = PriorTerm(prior, "vsd", (BandWeight(BandMask.full(), 1.0),), cfg_scale=cfg_scale, t_range=LATE_T)
    return GuidanceConfig((term,), LAMBDA_C, SIGMA)


def magic123(k3d: float = 1.0, k2d: float = 1.0) -> GuidanceConfig:
    """Magic123: N = 2 priors, SDS, Λ = I."""
    return GuidanceConfig((term_3d("sds", k3d), term_2d("sds", k2d, 0.0)), LAMBDA_C, SIGMA)


def paper_ablations() -> dict[str, GuidanceConfig]:
    """Every stage-2 row of the paper's ablations, keyed by a short name."""
    rows: dict[str, GuidanceConfig] = {
        "base": GuidanceConfig((term_3d(),), LAMBDA_C, SIGMA),
        "full_pass_2d": stage2_texture(r=0.0),
        "high_pass_2d_sds": stage2_texture(mode_2d="sds"),
        "ours": stage2_texture(),
        "finetuned_3d": stage2_texture(mode_3d="vsd"),
    }
    for k in (0, 1, 2, 3, 4, 5):
        rows[f"k2d={k}"] = stage2_texture(k2d=float(k))
    for r in (0.0, 0.2, 0.4, 0.6, 0.8, 1.0):
        rows[f"r={r:.1f}"] = stage2_texture(r=r)
    return rows
