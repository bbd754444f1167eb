"""The official loss reductions, term by term, against values computed by hand; the render settings
and the t-annealing reach what they configure."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest
import torch

from morpheus_core.guidance.frequency import BandMask, dct_matrix
from morpheus_core.guidance.loss_balance import LAMBDA_SCALE, mask_bce, reference_loss, scaled_total
from ops.config.presets import preset
from ops.stages.nerf import normal_smoothness


def _gen() -> torch.Generator:
    return torch.Generator().manual_seed(int(torch.randint(0, 2**31, ())))


def test_reference_loss_is_a_mean_over_each_views_elements() -> None:
    g = _gen()
    x, y = torch.rand(1, 3, 4, 5, generator=g, dtype=torch.float64), torch.rand(1, 3, 4, 5, generator=g,
                                                                                 dtype=torch.float64)
    by_hand = sum((float(a) - float(b)) ** 2 for a, b in zip(x.flatten(), y.flatten(), strict=True)) / 60
    assert float(reference_loss(x, y, BandMask.full())) == pytest.approx(by_hand, rel=1e-12)
    # A band: ‖Λ(V d Vᵀ)‖² written with explicit DCT matrices, over the same 60 elements.
    band = BandMask.high_pass(0.5)
    vh, vw = dct_matrix(4), dct_matrix(5)
    coeffs = vh @ (x - y)[0] @ vw.T
    keep = band.mask(4, 5).to(torch.float64)
    assert float(reference_loss(x, y, band)) == pytest.approx(float((coeffs * keep).pow(2).sum()) / 60, rel=1e-10)


def test_reference_loss_of_a_batch_is_the_sum_of_each_objects_mean() -> None:
    g = _gen()
    x, y = torch.rand(3, 3, 6, 6, generator=g), torch.rand(3, 3, 6, 6, generator=g)
    each = [float(((x[i] - y[i]) ** 2).mean()) for i in range(3)]
    assert float(reference_loss(x, y, BandMask.full(), objects=3)) == pytest.approx(sum(each), rel=1e-5)
    # Two reference views of one object: their mean, not their sum.
    assert float(reference_loss(x[:2], y[:2], BandMask.full())) == pytest.approx((each[0] + each[1]) / 2, rel=1e-5)


def test_mask_bce_is_a_mean_over_pixels() -> None:
    g = _gen()
    o = torch.rand(1, 1, 5, 7, generator=g) * 0.98 + 0.01
    m = (torch.rand(1, 1, 5, 7, generator=g) > 0.5).float()
    by_hand = -sum(math.log(p) if t else math.log(1 - p) for p, t in zip(o.flatten().tolist(),
                                                                          m.flatten().tolist(), strict=True)) / 35
    assert float(mask_bce(o, m)) == pytest.approx(by_hand, rel=1e-5)
    # Saturated opacities stay finite (clamped), with a finite gradient.
    extreme = torch.tensor([0.0, 1.0, 0.0, 1.0]).reshape(1, 1, 2, 2).requires_grad_()
    loss = mask_bce(extreme, torch.tensor([1.0, 0.0, 0.0, 1.0]).reshape(1, 1, 2, 2))
    loss.backward()
    assert math.isfinite(float(loss.detach())) and bool(torch.isfinite(extreme.grad).all())


def test_scaled_total_scales_the_3d_losses_only() -> None:
    g, e, f = (torch.rand((), generator=_gen()) for _ in range(3))
    assert float(scaled_total(g, e, f)) == pytest.approx(LAMBDA_SCALE * (float(g) + float(e)) + float(f), rel=1e-6)
    assert LAMBDA_SCALE == 1000.0


def test_normal_smoothness_is_a_mean_over_elements() -> None:
    normal = torch.randn(2, 3, 4, 3, generator=_gen())
    opacity = torch.ones(2, 3, 4, 1)
    dx = sum(float((normal[b, i, j + 1, c] - normal[b, i, j, c]) ** 2) for b in range(2) for i in range(3)
             for j in range(3) for c in range(3)) / (2 * 3 * 3 * 3)
    dy = sum(float((normal[b, i + 1, j, c] - normal[b, i, j, c]) ** 2) for b in range(2) for i in range(2)
             for j in range(4) for c in range(3)) / (2 * 2 * 4 * 3)
    assert float(normal_smoothness(normal, opacity)) == pytest.approx(dx + dy, rel=1e-5)


def test_hybrid_guidance_reference_term_has_the_official_weight() -> None:
    from morpheus_core.guidance.diffusion import NoiseSchedule
    from morpheus_core.guidance.hybrid import BandWeight, GuidanceConfig, PriorBinding, PriorTerm, hybrid_guidance
    from morpheus_core.guidance.prior_protocol import PixelSpacePrior

    class Zero(PixelSpacePrior):
        def predict_noise(self, noisy, t, condition, cfg_scale):
            return torch.zeros_like(noisy)

    g = _gen()
    novel = torch.rand(1, 3, 8, 8, generator=g)
    ref_render, ref = torch.rand(1, 3, 8, 8, generator=g), torch.rand(1, 3, 8, 8, generator=g)
    cfg = GuidanceConfig((PriorTerm("p", "sds", (BandWeight(BandMask.full(), 1.0),)),), lambda_c=5e-4)
    out = hybrid_guidance(cfg, {"p": PriorBinding(Zero())}, NoiseSchedule(), novel, 0, ref_render, ref,
                          generator=g)
    assert float(out.stats["term0/p/ref0"]) == pytest.approx(float(((ref_render - ref) ** 2).mean()), rel=1e-5)


def test_the_nerf_anneal_follows_the_steps_unless_set() -> None:
    cfg = preset("paper", ["nerf.loop.steps=2000"])
    t = cfg.nerf.guidance.t_range(cfg.nerf.loop.steps)
    assert t.bounds(0) == (0.02, 0.98) and t.bounds(1000) == (0.02, 0.5) and t.bounds(998)[1] > 0.5
    explicit = preset("paper", ["nerf.loop.steps=2000", "nerf.guidance.anneal_step=300"]).nerf.guidance
    assert explicit.t_range(2000).bounds(300) == (0.02, 0.5) and explicit.t_range(2000).bounds(298)[1] > 0.5
    assert preset("paper").nerf.guidance.t_range(10_000).bounds(5000) == (0.02, 0.5)
    with pytest.raises(ValueError, match="anneal_step"):
        preset("paper", ["nerf.guidance.anneal_step=-1"])


def test_every_render_setting_reaches_the_nerf_renderer(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import ops.stages.nerf as nerf_stage
    from assets_store.store import Store
    from ops.pipeline.runner import Pipeline, stages_until
    from tests.pipeline_helpers import PHOTOS, tiny_config

    sets = ["nerf.render.n_samples=13", "nerf.render.max_density=777.0", "nerf.render.chunk_points=4099",
            "nerf.render.normal_weight_threshold=0.003", "nerf.render.transmittance_threshold=0.002"]
    cfg = tiny_config(*sets, nerf=2)
    seen = []
    real = nerf_stage.render_volume

    def spy(field, cameras, h, w, config, *args, **kwargs):
        seen.append(config)
        return real(field, cameras, h, w, config, *args, **kwargs)

    monkeypatch.setattr(nerf_stage, "render_volume", spy)
    out = Pipeline(Store(tmp_path / "store"), cfg, "tiny").run([(PHOTOS / "mug.jpg", "mug")], stages_until("nerf"))[0]
    assert out.error is None, out.error
    assert seen
    for config in seen:  # every field as configured, except what a render is for (training or eval)
        for f in dataclasses.fields(config):
            if f.name not in ("stratified", "with_normals"):
                assert getattr(config, f.name) == getattr(cfg.nerf.render, f.name), f.name
    assert any(c.stratified for c in seen) and any(not c.stratified for c in seen)
