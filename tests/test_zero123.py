"""Zero123 3D prior: camera vector, conditioning inputs, CFG, cached reference, SDS gradient."""

from __future__ import annotations

import math

import pytest
import torch

from morpheus_core.guidance.diffusion import NoiseSchedule, apply_cfg
from morpheus_core.guidance.hybrid import PriorBinding, hybrid_guidance
from morpheus_core.guidance.presets import PRIOR_3D, stage1_dmtet
from morpheus_core.priors.zero123 import Camera, Zero123Prior, relative_camera
from tests.helpers import photo

SCHED = NoiseSchedule()


def _capture(module: torch.nn.Module) -> tuple[list[dict], object]:
    calls: list[dict] = []

    def hook(mod, args, kwargs):
        calls.append({"args": args, **kwargs})

    return calls, module.register_forward_pre_hook(hook, with_kwargs=True)


def test_camera_vector_for_known_angles() -> None:
    ref = torch.tensor([[0.0, 0.0, 2.5], [0.0, 0.0, 2.5], [10.0, -30.0, 2.0]])
    vec = relative_camera(torch.tensor([30.0, -45.0, 10.0]), torch.tensor([90.0, 180.0, 60.0]),
                          torch.tensor([3.0, 2.5, 2.0]), ref)
    want = torch.tensor([
        [-math.pi / 6, 1.0, 0.0, 0.5],   # 30° up: the polar angle drops by π/6; a quarter turn
        [math.pi / 4, 0.0, -1.0, 0.0],   # 45° down, half a turn
        [0.0, 1.0, 0.0, 0.0],            # same elevation, 90° further round
    ])
    assert torch.allclose(vec, want, atol=1e-6)


def test_reference_is_cached_once_with_unscaled_latents_on_white(zero123: Zero123Prior) -> None:
    calls, h = _capture(zero123.image_encoder)
    rgba = photo(1)
    zero123.set_reference("cache", rgba, Camera(5.0, 10.0, 2.5))
    assert len(calls) == 1
    on_white = rgba[:3] * rgba[3:] + (1 - rgba[3:])
    with torch.no_grad():
        ref = torch.nn.functional.interpolate(on_white[None], size=(256, 256), mode="bilinear",
                                              align_corners=False, antialias=False)
        mode = zero123.codec.vae.encode(ref * 2 - 1).latent_dist.mode()
    assert torch.allclose(zero123._latents["cache"], mode, atol=1e-5)  # no scaling factor
    x = torch.rand(2, 3, 64, 64, generator=torch.Generator().manual_seed(2))
    cond = zero123.condition(["cache", "cache"], torch.tensor([0.0, 20.0]), torch.tensor([40.0, -90.0]))
    for _ in range(3):
        zero123.predict_noise(zero123.encode(x).detach(), torch.tensor([200, 700]), cond, 3.0)
    h.remove()
    assert len(calls) == 1  # not per step
    assert torch.equal(cond.radius, torch.tensor([2.5, 2.5]))
    z = zero123.encode(x)
    up = torch.nn.functional.interpolate(x, size=(256, 256), mode="bilinear", align_corners=False)
    want = zero123.codec.vae.encode(up * 2 - 1).latent_dist.mode() * 0.18215  # scaled, differentiable path
    assert z.shape == (2, 4, 32, 32) and torch.allclose(z, want, atol=1e-5)


def test_unconditional_branch_zeroes_both_inputs_and_cfg_combines(zero123: Zero123Prior) -> None:
    g = torch.Generator().manual_seed(3)
    zero123.set_reference("cfg", photo(3))
    zt = torch.randn(2, 4, 32, 32, generator=g)
    t = torch.tensor([150, 600])
    cond = zero123.condition(["cfg", "cfg"], torch.tensor([15.0, -10.0]), torch.tensor([120.0, 30.0]))
    calls, h = _capture(zero123.unet)
    eps3 = zero123.predict_noise(zt, t, cond, 3.0)
    h.remove()
    sample, context = calls[0]["args"][0], calls[0]["encoder_hidden_states"]
    assert sample.shape == (4, 8, 32, 32) and context.shape[:2] == (4, 1)
    assert torch.equal(sample[:2, :4], zt) and torch.equal(sample[2:, :4], zt)
    assert not sample[:2, 4:].any() and not context[:2].any()  # unconditional: zeros for both
    assert sample[2:, 4:].any() and context[2:].any()
    with torch.no_grad():
        eps_u = zero123.unet(torch.cat([zt, torch.zeros_like(zt)], 1), t,
                             encoder_hidden_states=torch.zeros_like(context[2:])).sample
    eps_c = zero123.predict_noise(zt, t, cond, 1.0)
    assert torch.allclose(eps3, apply_cfg(eps_u, eps_c, 3.0), atol=1e-5)
    assert not torch.allclose(eps_u, eps_c, atol=1e-3)


def test_camera_and_reference_change_the_prediction(zero123: Zero123Prior) -> None:
    g = torch.Generator().manual_seed(4)
    zero123.set_reference("p", photo(4))
    zero123.set_reference("q", photo(5))
    zt, t = torch.randn(1, 4, 32, 32, generator=g), torch.tensor([300])
    e = lambda oid, az: zero123.predict_noise(zt, t, zero123.condition([oid], torch.zeros(1), torch.tensor([az])), 1.0)  # noqa: E731
    assert not torch.allclose(e("p", 0.0), e("p", 90.0), atol=1e-4)
    assert not torch.allclose(e("p", 0.0), e("q", 0.0), atol=1e-4)
    assert torch.isfinite(e("p", 0.0)).all()


def test_one_sds_step_backpropagates_a_finite_gradient_to_the_render(zero123: Zero123Prior) -> None:
    zero123.set_reference("sds", photo(6))
    g = torch.Generator().manual_seed(6)
    render = torch.rand(2, 3, 64, 64, generator=g, requires_grad=True)
    cond = zero123.condition(["sds", "sds"], torch.tensor([10.0, -20.0]), torch.tensor([45.0, 170.0]))
    out = hybrid_guidance(stage1_dmtet(), {PRIOR_3D: PriorBinding(zero123, condition=cond)}, SCHED, render, 0,
                          generator=g)
    out.loss.backward()
    assert torch.isfinite(out.loss) and torch.isfinite(render.grad).all() and render.grad.abs().sum() > 0


def test_unknown_object_and_bad_rows_raise(zero123: Zero123Prior) -> None:
    zt = torch.zeros(1, 4, 32, 32)
    with pytest.raises(KeyError, match="set_reference"):
        zero123.predict_noise(zt, torch.tensor([1]), zero123.condition(["nobody"], torch.zeros(1), torch.zeros(1),
                                                                        torch.ones(1)), 3.0)
    zero123.set_reference("rows", photo(7))
    with pytest.raises(ValueError, match="object ids"):
        zero123.predict_noise(torch.zeros(2, 4, 32, 32), torch.tensor([1, 2]),
                              zero123.condition(["rows"], torch.zeros(1), torch.zeros(1)), 3.0)
    with pytest.raises(ValueError, match="finite"):
        zero123.predict_noise(zt, torch.tensor([1]), zero123.condition(["rows"], torch.zeros(1), torch.zeros(1)),
                              float("nan"))
