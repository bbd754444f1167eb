"""The hybrid guidance with the real (tiny) priors: Morpheus3D, Magic123 and VSD configurations."""

from __future__ import annotations

import pytest
import torch

from morpheus_core.guidance.diffusion import NoiseSchedule
from morpheus_core.guidance.hybrid import PriorBinding, hybrid_guidance
from morpheus_core.guidance.presets import PRIOR_2D, PRIOR_3D, magic123, stage2_texture, vsd
from morpheus_core.priors.lora import ObjectLoras
from tests.helpers import photo

SCHED = NoiseSchedule()
IDS = ["m1", "m2"]


@pytest.fixture
def rig(zero123, load_image2d):
    prior2d = load_image2d()
    loras2d = ObjectLoras(prior2d)
    for i, oid in enumerate(IDS):
        ref = photo(60 + i)
        zero123.set_reference(oid, ref)
        prior2d.set_reference(oid, ref)
        loras2d.add(oid)
    return zero123, prior2d, loras2d


def _step(config, bindings, seed: int):
    g = torch.Generator().manual_seed(seed)
    novel = torch.rand(2, 3, 64, 64, generator=g, requires_grad=True)
    ref_render = torch.rand(2, 3, 64, 64, generator=g, requires_grad=True)
    reference = torch.stack([photo(60 + i, rgba=False) for i in range(2)])
    out = hybrid_guidance(config, bindings, SCHED, novel, 0, reference_render=ref_render, reference=reference,
                          generator=g)
    (out.loss + out.finetune_loss).backward()
    assert torch.isfinite(out.loss) and torch.isfinite(out.finetune_loss)
    assert torch.isfinite(novel.grad).all() and novel.grad.abs().sum() > 0
    assert torch.isfinite(ref_render.grad).all()
    return out, novel


def _bindings(zero123, prior2d, renders, finetuned2d=None, finetuned3d=None):
    cond3d = zero123.condition(IDS, torch.tensor([10.0, -15.0]), torch.tensor([60.0, -120.0]))
    return {PRIOR_3D: PriorBinding(zero123, finetuned3d, cond3d),
            PRIOR_2D: PriorBinding(prior2d, finetuned2d, prior2d.condition(IDS, renders))}


def test_morpheus3d_stage2_3d_sds_full_pass_plus_2d_vsd_high_pass(rig) -> None:
    zero123, prior2d, loras2d = rig
    config = stage2_texture()
    renders = torch.rand(2, 3, 64, 64, generator=torch.Generator().manual_seed(7))
    out, _ = _step(config, _bindings(zero123, prior2d, renders, loras2d), seed=1)
    assert float(out.finetune_loss.detach()) > 0 and "term1/2d/finetune_loss" in out.stats
    for oid in IDS:  # the ε-MSE reached both objects' adapters, and only the adapters
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in loras2d.parameters(oid))
    assert not any(p.requires_grad for p in zero123.unet.parameters())
    assert not loras2d.step().any()


def test_magic123_configuration(rig) -> None:
    zero123, prior2d, _ = rig
    renders = torch.rand(2, 3, 64, 64, generator=torch.Generator().manual_seed(8))
    out, _ = _step(magic123(), _bindings(zero123, prior2d, renders), seed=2)
    assert float(out.finetune_loss.detach()) == 0.0 and set(out.stats) >= {"term0/3d/grad_norm", "term1/2d/grad_norm"}


@pytest.mark.parametrize("role", [PRIOR_3D, PRIOR_2D])
def test_vsd_configuration(rig, role: str) -> None:
    zero123, prior2d, loras2d = rig
    renders = torch.rand(2, 3, 64, 64, generator=torch.Generator().manual_seed(9))
    if role == PRIOR_3D:  # VSD with the 3D prior needs its own LoRA on the Zero123 UNet
        loras = ObjectLoras(zero123)
        for oid in IDS:
            loras.add(oid)
        bindings = _bindings(zero123, prior2d, renders, finetuned3d=loras)
        config = vsd()
    else:
        loras = loras2d
        bindings = _bindings(zero123, prior2d, renders, finetuned2d=loras)
        config = vsd(PRIOR_2D, cfg_scale=2.0)
    try:
        out, _ = _step(config, bindings, seed=3)
        assert float(out.finetune_loss.detach()) > 0 and not loras.step().any()
    finally:
        if role == PRIOR_3D:  # the Zero123 fixture is shared: leave it without adapters
            for oid in IDS:
                loras.remove(oid)
