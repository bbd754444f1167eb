"""Hybrid guidance (Algorithm 1): closed-form gradients, Proposition 2, configurations, extremes."""

from __future__ import annotations

import itertools

import pytest
import torch

from morpheus_core.guidance.diffusion import NoiseSchedule, TimestepRange
from morpheus_core.guidance.frequency import BandMask, apply_band, dct2, frequency_reference_loss, idct2
from morpheus_core.guidance.hybrid import (
    BandWeight,
    GuidanceConfig,
    NonFiniteInputError,
    PriorBinding,
    PriorTerm,
    TermDraw,
    hybrid_guidance,
    inject_gradient,
)
from morpheus_core.guidance.presets import PRIOR_2D, PRIOR_3D, paper_ablations, stage2_texture
from tests.helpers import PooledPrior, RandomPrior, TinyFinetunedPrior

B, C, H, W = 2, 3, 12, 10
SCHED = NoiseSchedule()
LAMBDA_C, SIGMA = 0.3, 1.7  # away from the paper's values so every factor is exercised


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _images(seed: int, dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = _gen(seed)
    novel = torch.rand(B, C, H, W, generator=g, dtype=dtype).requires_grad_(True)
    ref_render = torch.rand(1, C, H, W, generator=g, dtype=dtype).requires_grad_(True)
    ref = torch.rand(1, C, H, W, generator=g, dtype=dtype)
    return novel, ref_render, ref


def _draw(seed: int, shape=(B, C, H, W), dtype=torch.float64, t=None) -> TermDraw:
    g = _gen(seed)
    tt = torch.randint(0, 1000, (shape[0],), generator=g) if t is None else t
    return TermDraw(
        tt,
        torch.randn(shape, generator=g, dtype=dtype),
        torch.randint(0, 1000, (shape[0],), generator=g),
        torch.randn(shape, generator=g, dtype=dtype),
    )


FILTERS = [BandWeight(BandMask.high_pass(0.4), 1.5), BandWeight(BandMask.low_pass(0.5), 0.7)]


def _config(mode: str, n_priors: int, n_filters: int) -> GuidanceConfig:
    terms = tuple(
        PriorTerm(f"p{n}", mode, tuple(FILTERS[:n_filters]) if n == 0 else tuple(FILTERS[::-1][:n_filters]),
                  cfg_scale=2.0 + n, finetuned_cfg_scale=1.0 + 0.5 * n)
        for n in range(n_priors)
    )
    return GuidanceConfig(terms, lambda_c=LAMBDA_C, sigma=SIGMA)


def _bindings(n_priors: int, finetuned: bool) -> dict[str, PriorBinding]:
    return {
        f"p{n}": PriorBinding(RandomPrior((C, H, W), seed=10 + n), TinyFinetunedPrior(C, seed=20 + n) if finetuned
                              else None)
        for n in range(n_priors)
    }


def _closed_form(config, bindings, novel, ref_render, ref, draws):
    """Eq. (6) written out with explicit DCT matrices: Σ_n Σ_m k·[λc w VΛVᵀ(ε_n − ε_φn)] and
    Σ_n Σ_m k·(1 − λc)/σ² · 2 VΛVᵀ(x_ref − y), each averaged over its batch; the reference term is a
    mean over each view's C·H·W elements too (the official reductions, ``loss_balance``)."""
    g_novel = torch.zeros_like(novel)
    g_ref = torch.zeros_like(ref_render)
    x = novel.detach()
    for term, draw in zip(config.terms, draws, strict=True):
        bind = bindings[term.prior]
        xt = SCHED.add_noise(x, draw.noise, draw.t)
        eps = bind.prior.predict_noise(xt, draw.t, None, term.cfg_scale)
        eps_phi = (bind.finetuned.predict_noise(xt, draw.t, None, term.finetuned_cfg_scale).detach()
                   if term.mode == "vsd" else draw.noise)
        ab = SCHED.alphas_cumprod[draw.t].reshape(-1, 1, 1, 1)
        for f in term.filters:
            r_filtered = idct2(apply_band(dct2(eps - eps_phi), f.band))
            g_novel += f.k * LAMBDA_C * (1 - ab) * r_filtered / x.shape[0]
            diff = (ref_render - ref).detach()
            g_ref += (f.k * (1 - LAMBDA_C) / SIGMA**2 * 2 * idct2(apply_band(dct2(diff), f.band))
                      / (ref.shape[0] * ref[0].numel()))
    return g_novel, g_ref


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm() / b.norm().clamp(min=1e-300))


@pytest.mark.parametrize("mode,n_priors,n_filters", list(itertools.product(["sds", "vsd"], [1, 2], [1, 2])))
def test_surrogate_gradient_equals_eq6(mode: str, n_priors: int, n_filters: int) -> None:
    config = _config(mode, n_priors, n_filters)
    bindings = _bindings(n_priors, finetuned=mode == "vsd")
    novel, ref_render, ref = _images(seed=n_priors * 10 + n_filters)
    draws = [_draw(100 + n) for n in range(n_priors)]
    out = hybrid_guidance(config, bindings, SCHED, novel, step=0, reference_render=ref_render, reference=ref,
                          draws=draws)
    out.loss.backward()
    want_novel, want_ref = _closed_form(config, bindings, novel, ref_render, ref, draws)
    assert _rel(novel.grad, want_novel) < 1e-10
    assert _rel(ref_render.grad, want_ref) < 1e-10
    assert set(out.stats) >= {"term0/p0/grad_norm", "term0/p0/t_mean"}


def test_gradient_flows_through_the_prior_encoder() -> None:
    """A latent prior: the render receives Jᵀ g, J the encoder's Jacobian (here 2× pooling ×2)."""
    hh, ww = 8, 6
    prior = PooledPrior((C, hh // 2, ww // 2), seed=3)
    config = GuidanceConfig((PriorTerm("p", "sds", (BandWeight(BandMask.high_pass(0.5), 2.0),), cfg_scale=3.0),),
                            lambda_c=LAMBDA_C)
    novel = torch.rand(B, C, hh, ww, generator=_gen(1), dtype=torch.float64, requires_grad=True)
    draw = _draw(7, shape=(B, C, hh // 2, ww // 2))
    hybrid_guidance(config, {"p": PriorBinding(prior)}, SCHED, novel, 0, draws=[draw]).loss.backward()
    z0 = prior.encode(novel.detach())
    eps = prior.predict_noise(SCHED.add_noise(z0, draw.noise, draw.t), draw.t, None, 3.0)
    ab = SCHED.alphas_cumprod[draw.t].reshape(-1, 1, 1, 1)
    g = 2.0 * LAMBDA_C * (1 - ab) * idct2(apply_band(dct2(eps - draw.noise), BandMask.high_pass(0.5))) / B
    want = torch.nn.functional.interpolate(g, scale_factor=2, mode="nearest") * 2.0 / 4.0
    assert _rel(novel.grad, want) < 1e-10


def test_proposition2_reference_guidance_identity_band_equals_spatial() -> None:
    x = torch.rand(2, 3, 16, 14, generator=_gen(0), dtype=torch.float64, requires_grad=True)
    y = torch.rand(2, 3, 16, 14, generator=_gen(1), dtype=torch.float64)
    identity = BandMask.custom(torch.ones(16, 14, dtype=torch.bool))  # forces the DCT path
    (g_freq,) = torch.autograd.grad(frequency_reference_loss(x, y, identity), x)
    (g_spatial,) = torch.autograd.grad((x - y).pow(2).sum(), x)
    assert _rel(g_freq, g_spatial) < 1e-6


@pytest.mark.parametrize("mode", ["sds", "vsd"])
def test_proposition2_prior_guidance_identity_band_equals_spatial(mode: str) -> None:
    identity = BandMask.custom(torch.ones(H, W, dtype=torch.bool))
    term = PriorTerm("p", mode, (BandWeight(identity, 1.0),), cfg_scale=3.0)
    bindings = _bindings(1, finetuned=True)
    bindings = {"p": bindings["p0"]}
    novel, ref_render, ref = _images(seed=3)
    draw = _draw(11)
    out = hybrid_guidance(GuidanceConfig((term,), LAMBDA_C, SIGMA), bindings, SCHED, novel, 0,
                          reference_render=ref_render, reference=ref, draws=[draw])
    out.loss.backward()
    # Spatial form of Proposition 1: λc w (ε − ε_φ) and (1 − λc)/σ² ∇‖x_ref − y‖², no transform at all.
    xt = SCHED.add_noise(novel.detach(), draw.noise, draw.t)
    eps = bindings["p"].prior.predict_noise(xt, draw.t, None, 3.0)
    eps_phi = bindings["p"].finetuned.predict_noise(xt, draw.t, None, 1.0).detach() if mode == "vsd" else draw.noise
    ab = SCHED.alphas_cumprod[draw.t].reshape(-1, 1, 1, 1)
    assert _rel(novel.grad, LAMBDA_C * (1 - ab) * (eps - eps_phi) / B) < 1e-6
    elements = ref_render[0].numel()  # the reference term is a mean over C·H·W
    assert _rel(ref_render.grad, (1 - LAMBDA_C) / SIGMA**2 * 2 * (ref_render - ref).detach() / elements) < 1e-6


def test_vsd_finetune_loss_trains_only_the_counterpart() -> None:
    config = _config("vsd", 1, 1)
    bindings = _bindings(1, finetuned=True)
    ft = bindings["p0"].finetuned
    novel, _, _ = _images(seed=5)
    draw = _draw(13)
    out = hybrid_guidance(config, bindings, SCHED, novel, 0, draws=[draw])
    out.loss.backward(retain_graph=True)
    assert ft.conv.weight.grad is None  # θ's surrogate never reaches φ
    grad_novel = novel.grad.clone()
    out.finetune_loss.backward()
    assert ft.conv.weight.grad is not None and ft.conv.weight.grad.abs().sum() > 0
    assert torch.equal(novel.grad, grad_novel)  # φ's loss never reaches θ
    zft = SCHED.add_noise(novel.detach(), draw.finetune_noise, draw.finetune_t)
    want = (ft.predict_noise(zft, draw.finetune_t, None, 1.0) - draw.finetune_noise).pow(2).mean()
    assert torch.allclose(out.finetune_loss, want.detach())


def test_sampled_draws_are_reproducible_and_in_range() -> None:
    config = GuidanceConfig((PriorTerm("p", "sds", (BandWeight(BandMask.full(), 1.0),),
                                       t_range=TimestepRange(0.02, 0.5)),))
    bindings = {"p": PriorBinding(RandomPrior((C, H, W), 1, torch.float32))}
    grads = []
    for _ in range(2):
        novel = torch.rand(B, C, H, W, generator=_gen(0), requires_grad=True)
        out = hybrid_guidance(config, bindings, SCHED, novel, 0, generator=_gen(42))
        out.loss.backward()
        grads.append(novel.grad)
        assert 20 <= float(out.stats["term0/p/t_mean"]) <= 500
    assert torch.equal(grads[0], grads[1])


class _Constant(RandomPrior):
    def __init__(self, value: float) -> None:
        super().__init__((C, H, W), 0)
        self.value = value

    def predict_noise(self, noisy, t, condition, cfg_scale):
        return torch.full_like(noisy, self.value)


class _MustNotRun(RandomPrior):
    def predict_noise(self, noisy, t, condition, cfg_scale):
        raise AssertionError("a term with no weight must not evaluate its prior")


@pytest.mark.parametrize("value", [1e6, -1e30, float("nan"), float("inf")])
def test_extreme_and_nonfinite_prior_outputs_give_finite_gradients(value: float) -> None:
    term = PriorTerm("p", "sds", (BandWeight(BandMask.high_pass(0.6), 3.0),))
    for clip in (None, 1e-3):
        novel = torch.rand(B, C, H, W, generator=_gen(0), requires_grad=True)
        out = hybrid_guidance(GuidanceConfig((term,), grad_clip=clip), {"p": PriorBinding(_Constant(value))},
                              SCHED, novel, 0, generator=_gen(1))
        out.loss.backward()
        assert torch.isfinite(out.loss) and torch.isfinite(novel.grad).all()
        if clip is not None:
            assert novel.grad.abs().max() <= clip + 1e-9


@pytest.mark.parametrize("t", [0, 999])
def test_timestep_extremes_are_finite(t: int) -> None:
    config = _config("vsd", 2, 2)
    novel, ref_render, ref = _images(seed=1)
    draws = [_draw(n, t=torch.full((B,), t)) for n in range(2)]
    out = hybrid_guidance(config, _bindings(2, True), SCHED, novel, 0, reference_render=ref_render, reference=ref,
                          draws=draws)
    (out.loss + out.finetune_loss).backward()
    assert torch.isfinite(novel.grad).all() and torch.isfinite(ref_render.grad).all()
    assert torch.isfinite(out.loss) and torch.isfinite(out.finetune_loss)


def test_zero_weight_and_null_band_terms_are_skipped_and_contribute_nothing() -> None:
    base_term = PriorTerm("p", "sds", (BandWeight(BandMask.full(), 1.0),))
    bindings = {"p": PriorBinding(RandomPrior((C, H, W), 4)), "off": PriorBinding(_MustNotRun((C, H, W), 5))}
    draw = _draw(3)
    grads = []
    for off_filters in [None, (BandWeight(BandMask.high_pass(0.6), 0.0),), (BandWeight(BandMask.null(), 2.0),)]:
        terms = (base_term,) if off_filters is None else (base_term, PriorTerm("off", "sds", off_filters))
        novel, ref_render, ref = _images(seed=2)
        out = hybrid_guidance(GuidanceConfig(terms), bindings, SCHED, novel, 0, reference_render=ref_render,
                              reference=ref, draws=[draw] * len(terms))
        out.loss.backward()
        grads.append((novel.grad, ref_render.grad))
    for g_novel, g_ref in grads[1:]:
        assert torch.equal(g_novel, grads[0][0]) and torch.equal(g_ref, grads[0][1])


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_renders(dtype: torch.dtype) -> None:
    config = stage2_texture()
    bindings = {
        PRIOR_3D: PriorBinding(RandomPrior((C, H, W), 1, torch.float32)),
        PRIOR_2D: PriorBinding(RandomPrior((C, H, W), 2, torch.float32), TinyFinetunedPrior(C, 3, torch.float32)),
    }
    bindings[PRIOR_2D].finetuned.to(dtype)
    novel = torch.rand(B, C, H, W, generator=_gen(0)).to(dtype).requires_grad_(True)
    ref_render = torch.rand(1, C, H, W, generator=_gen(1)).to(dtype).requires_grad_(True)
    ref = torch.rand(1, C, H, W, generator=_gen(2)).to(dtype)
    out = hybrid_guidance(config, bindings, SCHED, novel, 0, reference_render=ref_render, reference=ref,
                          generator=_gen(3))
    (out.loss + out.finetune_loss).backward()
    assert novel.grad.dtype == dtype and torch.isfinite(novel.grad).all() and novel.grad.abs().sum() > 0
    assert torch.isfinite(ref_render.grad).all() and torch.isfinite(out.finetune_loss)


def test_invalid_inputs_raise_clear_errors() -> None:
    config = _config("vsd", 1, 1)
    novel, ref_render, ref = _images(seed=0)
    with pytest.raises(KeyError, match="p0"):
        hybrid_guidance(config, {}, SCHED, novel, 0)
    with pytest.raises(ValueError, match="fine-tuned"):
        hybrid_guidance(config, _bindings(1, finetuned=False), SCHED, novel, 0)
    with pytest.raises(ValueError, match="both"):
        hybrid_guidance(config, _bindings(1, True), SCHED, novel, 0, reference=ref)
    with pytest.raises(ValueError, match="draws"):
        hybrid_guidance(config, _bindings(1, True), SCHED, novel, 0, draws=[_draw(0), _draw(1)])
    bad = novel.detach().clone()
    bad[0, 0, 0, 0] = float("nan")
    with pytest.raises(NonFiniteInputError, match="novel-view render"):
        hybrid_guidance(config, _bindings(1, True), SCHED, bad, 0)
    bad_ref = ref.clone()
    bad_ref[..., 3] = float("inf")
    with pytest.raises(NonFiniteInputError, match="reference image"):
        hybrid_guidance(config, _bindings(1, True), SCHED, novel, 0, reference_render=ref_render, reference=bad_ref)
    with pytest.raises(ValueError):
        GuidanceConfig(())
    with pytest.raises(ValueError):
        GuidanceConfig(config.terms, lambda_c=1.5)
    with pytest.raises(ValueError):
        BandWeight(BandMask.full(), -1.0)
    with pytest.raises(ValueError):
        PriorTerm("p", "dds", (BandWeight(BandMask.full(), 1.0),))
    with pytest.raises(ValueError, match="does not match"):
        inject_gradient(torch.zeros(3), torch.zeros(4))


def test_paper_configurations() -> None:
    ours = stage2_texture()
    t3, t2 = ours.terms
    assert (ours.lambda_c, ours.sigma) == (5e-4, 1.0)
    assert (t3.prior, t3.mode, t3.cfg_scale, t3.filters) == (PRIOR_3D, "sds", 3.0, (BandWeight(BandMask.full(), 1.0),))
    assert (t2.prior, t2.mode, t2.cfg_scale, t2.finetuned_cfg_scale) == (PRIOR_2D, "vsd", 2.0, 1.0)
    assert t2.filters == (BandWeight(BandMask.high_pass(0.6), 3.0),)
    assert t3.t_range.bounds(0) == t2.t_range.bounds(0) == (0.02, 0.5)
    rows = paper_ablations()
    expected = {"base", "full_pass_2d", "high_pass_2d_sds", "ours", "finetuned_3d"}
    expected |= {f"k2d={k}" for k in range(6)} | {f"r={r:.1f}" for r in (0, 0.2, 0.4, 0.6, 0.8, 1.0)}
    assert set(rows) == expected


def _ablation_grads(config: GuidanceConfig) -> tuple[torch.Tensor, torch.Tensor]:
    bindings = {
        PRIOR_3D: PriorBinding(RandomPrior((C, H, W), 1), TinyFinetunedPrior(C, 5)),
        PRIOR_2D: PriorBinding(RandomPrior((C, H, W), 2), TinyFinetunedPrior(C, 6)),
    }
    draws = {PRIOR_3D: _draw(31), PRIOR_2D: _draw(32)}
    novel, ref_render, ref = _images(seed=9)
    out = hybrid_guidance(config, bindings, SCHED, novel, 0, reference_render=ref_render, reference=ref,
                          draws=[draws[t.prior] for t in config.terms])
    (out.loss + out.finetune_loss).backward()
    assert torch.isfinite(novel.grad).all()
    return novel.grad, ref_render.grad


def test_ablation_rows_run_and_their_equivalences_hold() -> None:
    rows = paper_ablations()
    grads = {name: _ablation_grads(cfg) for name, cfg in rows.items()}
    for a, b in [("k2d=0", "base"), ("r=1.0", "base"), ("r=0.0", "full_pass_2d"), ("ours", "r=0.6"),
                 ("ours", "k2d=3")]:
        assert torch.allclose(grads[a][0], grads[b][0], atol=1e-14), (a, b)
        assert torch.allclose(grads[a][1], grads[b][1], atol=1e-14), (a, b)
    assert not torch.allclose(grads["ours"][0], grads["full_pass_2d"][0])
    assert not torch.allclose(grads["ours"][0], grads["high_pass_2d_sds"][0])


def test_paper_rows_hold_the_papers_numbers() -> None:
    """The rows are changes to the texture stage's settings; written out, they are the paper's terms."""
    from morpheus_core.guidance.diffusion import TimestepRange
    from morpheus_core.guidance.hybrid import GuidanceConfig
    from morpheus_core.guidance.presets import term_2d, term_3d

    late = TimestepRange(0.02, 0.5)
    three_d = term_3d("sds", 1.0, late, 3.0, 1.0)
    rows = paper_ablations()
    assert rows["ours"] == GuidanceConfig((three_d, term_2d("vsd", 3.0, 0.6, late, 2.0, 1.0)), 5e-4, 1.0)
    assert rows["base"] == GuidanceConfig((three_d,), 5e-4, 1.0)
    assert rows["k2d=0"].terms[1].filters[0].k == 0.0 and rows["r=1.0"].terms[1].filters[0].band.kind == "null"
    assert rows["full_pass_2d"].terms[1].filters[0].band.kind == "full"
    assert rows["finetuned_3d"].terms[0].mode == "vsd" and rows["high_pass_2d_sds"].terms[1].mode == "sds"
