"""Prior runtime settings: validation, device defaults, VAE precision, placement."""

from __future__ import annotations

import pytest
import torch

from morpheus_core.priors.runtime import PriorRuntime


def test_runtime_defaults_and_validation() -> None:
    cpu = PriorRuntime.for_device("cpu")
    assert (cpu.dtype, cpu.accel, cpu.channels_last, cpu.vae_precision) == (torch.float32, "eager", False,
                                                                              torch.float32)
    gpu = PriorRuntime.for_device("cuda:0", accel="cudagraph")
    assert (gpu.dtype, gpu.channels_last, gpu.accel) == (torch.float16, True, "cudagraph")
    assert gpu.vae_precision == torch.float32  # the SD VAE overflows in float16
    assert PriorRuntime("cuda", torch.bfloat16).vae_precision == torch.bfloat16
    assert PriorRuntime("cuda", torch.float16, vae_dtype=torch.float16).vae_precision == torch.float16
    with pytest.raises(ValueError, match="CUDA"):
        PriorRuntime("cpu", accel="cudagraph")
    with pytest.raises(ValueError, match="dtype"):
        PriorRuntime(dtype=torch.float64)
    with pytest.raises(ValueError, match="vae_dtype"):
        PriorRuntime(vae_dtype=torch.float64)


def test_priors_config_sets_the_vae_precision_apart_from_the_priors() -> None:
    from ops.engine.priors import PriorsConfig

    rt = PriorsConfig(dtype="float32", vae_dtype="bfloat16").runtime(torch.device("cpu"))
    assert (rt.dtype, rt.vae_precision, rt.accel) == (torch.float32, torch.bfloat16, "eager")
    assert PriorsConfig().runtime(torch.device("cpu")).vae_precision == torch.float32


def test_bfloat16_vae_encodes_close_to_float32_with_float32_latents(registry) -> None:
    """The precision the VAE runs in on a GPU, checked against float32 on the tiny SD VAE: latents and
    the gradient back into the renders (what the guidance trains on)."""
    from morpheus_core.priors.image2d import Image2DPrior, Image2DSettings
    from tests.helpers import RES_2D

    priors = [Image2DPrior.from_registry(registry, PriorRuntime(vae_dtype=d), Image2DSettings(resolution=RES_2D))
              for d in (torch.float32, torch.bfloat16)]
    assert [p.codec.vae.dtype for p in priors] == [torch.float32, torch.bfloat16]
    priors[1].codec.vae.load_state_dict(priors[0].codec.vae.state_dict())
    g = torch.Generator().manual_seed(11)
    images = torch.rand(2, 4, RES_2D, RES_2D, generator=g)
    weights = None
    got = []
    for prior in priors:
        x = images.clone().requires_grad_(True)
        z = prior.encode(x)
        weights = torch.randn(z.shape, generator=g) if weights is None else weights
        (z * weights).sum().backward()
        assert z.dtype == torch.float32 and torch.isfinite(x.grad).all()
        got.append((z.detach(), x.grad))
    (z32, g32), (z16, g16) = got
    assert float((z16 - z32).norm() / z32.norm()) < 0.02
    assert float(torch.nn.functional.cosine_similarity(g16.flatten(), g32.flatten(), dim=0)) > 0.99


def test_place_freezes_and_casts() -> None:
    lin = PriorRuntime(dtype=torch.bfloat16).place(torch.nn.Linear(3, 2))
    assert lin.weight.dtype == torch.bfloat16 and not lin.weight.requires_grad and not lin.training


def test_lru_cache_drops_the_least_recently_used_entry() -> None:
    from morpheus_core.runtime.cuda_graphs import LruCache

    cache: LruCache[str, int] = LruCache(2)
    cache.put("a", 1)
    cache.put("b", 2)
    assert cache.get("a") == 1  # "a" is now the most recent
    cache.put("c", 3)
    assert cache.get("b") is None and cache.get("a") == 1 and cache.get("c") == 3 and len(cache) == 2
    with pytest.raises(ValueError, match="cache size"):
        LruCache(0)
