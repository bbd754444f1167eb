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
    with pytest.raises(ValueError, match="CUDA"):
        PriorRuntime("cpu", accel="cudagraph")
    with pytest.raises(ValueError, match="dtype"):
        PriorRuntime(dtype=torch.float64)


def test_place_freezes_and_casts() -> None:
    lin = PriorRuntime(dtype=torch.bfloat16).place(torch.nn.Linear(3, 2))
    assert lin.weight.dtype == torch.bfloat16 and not lin.weight.requires_grad and not lin.training


def test_lru_cache_drops_the_least_recently_used_entry() -> None:
    from morpheus_core.cuda_graphs import LruCache

    cache: LruCache[str, int] = LruCache(2)
    cache.put("a", 1)
    cache.put("b", 2)
    assert cache.get("a") == 1  # "a" is now the most recent
    cache.put("c", 3)
    assert cache.get("b") is None and cache.get("a") == 1 and cache.get("c") == 3 and len(cache) == 2
    with pytest.raises(ValueError, match="cache size"):
        LruCache(0)
