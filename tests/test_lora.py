"""VSD LoRA: scale 0 is the frozen UNet, the ε-MSE falls, one adapter per object, checkpoints."""

from __future__ import annotations

import itertools
from collections.abc import Callable
from pathlib import Path

import pytest
import torch

from morpheus_core.guidance.diffusion import NoiseSchedule
from morpheus_core.priors.image2d import Image2DPrior
from morpheus_core.priors.lora import LoraSettings, ObjectLoras, adapter_name
from tests.helpers import photo

SCHED = NoiseSchedule()


def _setup(load: Callable[[], Image2DPrior], ids=("a", "b")) -> tuple[Image2DPrior, ObjectLoras]:
    prior = load()
    loras = ObjectLoras(prior)
    for i, oid in enumerate(ids):
        prior.set_reference(oid, photo(20 + i))
        loras.add(oid)
    return prior, loras


def _inputs(prior: Image2DPrior, ids: list[str], seed: int):
    g = torch.Generator().manual_seed(seed)
    renders = torch.rand(len(ids), 3, 64, 64, generator=g)
    z0 = prior.encode(renders).detach()
    noise = torch.randn(z0.shape, generator=g)
    t = torch.randint(0, 1000, (len(ids),), generator=g)
    return SCHED.add_noise(z0, noise, t), t, noise, prior.condition(ids, renders)


def _train(loras: ObjectLoras, zt, t, noise, cond, steps: int) -> list[float]:
    losses = []
    for _ in range(steps):
        loss = (loras.predict_noise(zt, t, cond, 1.0) - noise).pow(2).mean()
        loss.backward()
        assert not loras.step().any()
        losses.append(float(loss.detach()))
    return losses


def test_lora_loss_decreases_on_a_fixed_input(load_image2d) -> None:
    prior, loras = _setup(load_image2d, ("a",))
    assert loras.settings == LoraSettings(rank=4, alpha=4.0, lr=1e-4)
    zt, t, noise, cond = _inputs(prior, ["a", "a"], 0)
    losses = _train(loras, zt, t, noise, cond, 6)
    assert all(b < a for a, b in itertools.pairwise(losses)), losses


def test_adapter_scale_zero_reproduces_the_frozen_unet_exactly(load_image2d) -> None:
    prior, loras = _setup(load_image2d, ("a",))
    zt, t, noise, cond = _inputs(prior, ["a"], 1)
    fresh = load_image2d()  # a UNet that never had an adapter
    fresh.set_reference("a", photo(20))
    before = prior.predict_noise(zt, t, cond, 2.0)
    _train(loras, zt, t, noise, cond, 3)
    lora_b = loras.parameters("a")[1::2]  # (A, B) per layer; B starts at zero
    assert any(p.abs().sum() > 0 for p in lora_b)  # the adapter is no longer the identity
    assert not torch.allclose(loras.predict_noise(zt, t, cond, 1.0), prior.predict_noise(zt, t, cond, 1.0))
    frozen = prior.predict_noise(zt, t, cond, 2.0)
    assert torch.equal(frozen, before) and torch.equal(frozen, fresh.predict_noise(zt, t, cond, 2.0))
    # peft's own scale knob: adapter on at scale 0 is bit-identical to the frozen forward.
    tokens = prior.tokens(["a"])
    kwargs = dict(encoder_hidden_states=tokens.context, added_cond_kwargs={"image_embeds": [tokens.image_embeds]})
    unet = prior.unet
    with torch.no_grad():
        base = unet(zt, t, **kwargs).sample
        unet.enable_adapters()
        unet.set_adapter(adapter_name("a"))
        scaled0 = unet(zt, t, cross_attention_kwargs={"scale": 0.0}, **kwargs).sample
        scaled1 = unet(zt, t, **kwargs).sample
        unet.disable_adapters()
    assert torch.equal(scaled0, base) and not torch.allclose(scaled1, base)


def test_row_batched_adapters_equal_peft_native_forward(load_image2d) -> None:
    prior, loras = _setup(load_image2d, ("a", "b", "c"))
    g = torch.Generator().manual_seed(5)
    with torch.no_grad():
        for oid in loras.object_ids:  # distinct, non-zero adapters
            for p in loras.parameters(oid):
                p.normal_(0.0, 0.3, generator=g)
    ids = ["b", "a", "c", "b"]
    zt, t, _, cond = _inputs(prior, ids, 2)
    batched = loras.predict_noise(zt, t, cond, 2.0)
    unet = prior.unet
    for i, oid in enumerate(ids):
        unet.enable_adapters()
        unet.set_adapter(adapter_name(oid))
        row = type(cond)((oid,), cond.control[i: i + 1])
        native = prior.predict_noise(zt[i: i + 1], t[i: i + 1], row, 2.0)  # peft applies the active adapter
        unet.disable_adapters()
        assert torch.allclose(batched[i: i + 1], native, atol=1e-5), oid


def test_each_object_trains_only_its_own_adapter(load_image2d) -> None:
    prior, loras = _setup(load_image2d, ("a", "b"))
    b_before = [p.detach().clone() for p in loras.parameters("b")]
    zt, t, noise, cond = _inputs(prior, ["a", "a"], 3)
    loss = (loras.predict_noise(zt, t, cond, 1.0) - noise).pow(2).mean()
    loss.backward()
    assert all(p.grad is None for p in loras.parameters("b"))
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in loras.parameters("a"))
    assert all(p.requires_grad for p in loras.parameters("a") + loras.parameters("b"))
    assert not any(p.requires_grad for p in prior.controlnet.parameters())
    loras.step()
    assert all(torch.equal(p, q) for p, q in zip(loras.parameters("b"), b_before, strict=True))
    loras.remove("b")
    assert loras.object_ids == ("a",)
    with pytest.raises(KeyError, match="add"):
        loras.parameters("b")


def test_nonfinite_gradients_skip_the_step(load_image2d) -> None:
    _prior, loras = _setup(load_image2d, ("a",))
    before = [p.detach().clone() for p in loras.parameters("a")]
    for p in loras.parameters("a"):
        p.grad = torch.full_like(p, float("nan"))
    assert loras.step().tolist() == [True]
    assert all(torch.equal(p, q) for p, q in zip(loras.parameters("a"), before, strict=True))


def test_adapter_checkpoint_round_trip(load_image2d, tmp_path: Path) -> None:
    prior, loras = _setup(load_image2d, ("obj.with.dots",))
    zt, t, noise, cond = _inputs(prior, ["obj.with.dots"], 4)
    _train(loras, zt, t, noise, cond, 2)
    path = loras.save("obj.with.dots", tmp_path / "lora" / "obj.safetensors")
    assert [p.name for p in path.parent.iterdir()] == ["obj.safetensors"]  # no temporary left behind
    prior2 = load_image2d()
    prior2.set_reference("obj.with.dots", photo(20))
    loras2 = ObjectLoras(prior2)
    loras2.load("obj.with.dots", path)
    assert torch.allclose(loras2.predict_noise(zt, t, cond, 1.0), loras.predict_noise(zt, t, cond, 1.0), atol=1e-6)
    with pytest.raises(ValueError, match="rank"):
        ObjectLoras(load_image2d(), LoraSettings(rank=8)).load("x", path)


def test_real_suite_close_is_idempotent_and_frees_the_adapter(load_image2d) -> None:
    """A stage whose start fails closes its suite, and so may the caller that made it."""
    from ops.engine.priors import ModelCache, PriorsConfig, RealSuite

    prior = load_image2d()
    cfg = PriorsConfig()
    suite = RealSuite(cfg, torch.device("cpu"), "obj", photo(3), ("2d",), ("2d",), {"2d": prior})
    loras = ModelCache.loras(prior, cfg.lora)
    assert loras.object_ids == ("obj",)
    suite.close()
    suite.close()
    assert loras.object_ids == ()
    RealSuite(cfg, torch.device("cpu"), "obj", photo(3), ("2d",), ("2d",), {"2d": prior}).close()  # re-addable
