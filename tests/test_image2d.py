"""Image-prompt 2D prior: Canny control, ControlNet residuals, IP-Adapter tokens, CFG."""

from __future__ import annotations

import cv2
import numpy as np
import torch

from morpheus_core.guidance.diffusion import apply_cfg
from morpheus_core.imaging import canny_edges
from morpheus_core.priors.image2d import Image2DPrior
from morpheus_core.priors.image_prompt import ImagePromptEncoder, IPAdapterEncoder
from tests.helpers import RES_2D, photo


def _capture(module: torch.nn.Module) -> tuple[list[dict], object]:
    calls: list[dict] = []
    return calls, module.register_forward_pre_hook(lambda m, a, k: calls.append({"args": a, **k}), with_kwargs=True)


def _square(size: int = 64, contrast: float = 0.8) -> torch.Tensor:
    img = torch.full((1, 3, size, size), 0.1)
    img[..., size // 4: 3 * size // 4, size // 4: 3 * size // 4] += contrast
    return img


def test_canny_control_is_computed_from_the_render() -> None:
    render = _square()
    control = canny_edges(render, 64)
    assert control.shape == (1, 3, 64, 64) and set(control.unique().tolist()) <= {0.0, 1.0}
    assert torch.equal(control[:, 0], control[:, 1]) and torch.equal(control[:, 0], control[:, 2])
    frame = (render[0].permute(1, 2, 0) * 255).round().to(torch.uint8).numpy()
    want = cv2.Canny(np.ascontiguousarray(frame), 150, 250) / 255.0
    assert np.array_equal(control[0, 0].numpy(), want)
    rows = control[0, 0].nonzero()[:, 0]
    assert control.sum() > 0 and rows.min() >= 14 and rows.max() <= 49  # edges at the square's border only
    # A step of 26 grey levels gives a Sobel response of at most 4·26 = 104 < 150: no edges.
    assert canny_edges(_square(contrast=0.1), 64).sum() == 0
    assert canny_edges(_square(size=32), 64).shape == (1, 3, 64, 64)  # resized to the prior's resolution


def test_condition_uses_the_current_render(image2d: Image2DPrior) -> None:
    cond = image2d.condition(["a"], _square())
    assert cond.object_ids == ("a",) and torch.equal(cond.control, canny_edges(_square(), RES_2D))


def test_controlnet_residuals_reach_the_unet(image2d: Image2DPrior) -> None:
    image2d.set_reference("cn", photo(11))
    g = torch.Generator().manual_seed(11)
    zt, t = torch.randn(1, 4, 8, 8, generator=g), torch.tensor([400])
    calls, h = _capture(image2d.unet)
    edges = image2d.predict_noise(zt, t, image2d.condition(["cn"], _square()), 1.0)
    h.remove()
    down, mid = calls[0]["down_block_additional_residuals"], calls[0]["mid_block_additional_residual"]
    assert len(down) == len(image2d.unet.config.block_out_channels) * 2 and all(d.abs().sum() > 0 for d in down)
    assert mid.abs().sum() > 0
    blank = image2d.predict_noise(zt, t, image2d.condition(["cn"], torch.full((1, 3, 64, 64), 0.5)), 1.0)
    assert not torch.allclose(edges, blank, atol=1e-4)


def test_ip_adapter_tokens_change_the_output_and_cfg_zeroes_them(image2d: Image2DPrior) -> None:
    assert isinstance(image2d.encoder, ImagePromptEncoder) and isinstance(image2d.encoder, IPAdapterEncoder)
    assert image2d.unet.config.encoder_hid_dim_type == "ip_image_proj"
    image2d.set_reference("ip1", photo(12))
    image2d.set_reference("ip2", photo(13))
    g = torch.Generator().manual_seed(12)
    zt, t = torch.randn(1, 4, 8, 8, generator=g), torch.tensor([300])
    control = _square()
    e1 = image2d.predict_noise(zt, t, image2d.condition(["ip1"], control), 1.0)
    e2 = image2d.predict_noise(zt, t, image2d.condition(["ip2"], control), 1.0)
    assert not torch.allclose(e1, e2, atol=1e-4)
    calls, h = _capture(image2d.unet)
    e_cfg = image2d.predict_noise(zt, t, image2d.condition(["ip1"], control), 2.0)
    h.remove()
    embeds = calls[0]["added_cond_kwargs"]["image_embeds"][0]
    assert embeds.shape[:2] == (2, 1) and not embeds[0].any() and embeds[1].any()
    ctx = calls[0]["encoder_hidden_states"]
    assert torch.equal(ctx[0], ctx[1]) and torch.equal(ctx[0], image2d.encoder.null_context[0])
    tokens = image2d.tokens(["ip1"])
    e_u = image2d._denoise(zt, t, image2d.condition(["ip1"], control).control,
                           tokens.context, torch.zeros_like(tokens.image_embeds))
    assert torch.allclose(e_cfg, apply_cfg(e_u.detach(), e1, 2.0), atol=1e-5)


def test_one_encode_is_differentiable_and_finite(image2d: Image2DPrior) -> None:
    x = torch.rand(2, 3, 96, 96, generator=torch.Generator().manual_seed(14), requires_grad=True)
    z = image2d.encode(x)
    assert z.shape == (2, 4, 8, 8)
    z.square().sum().backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    assert image2d.decode(z.detach()).shape == (2, 3, 64, 64)
