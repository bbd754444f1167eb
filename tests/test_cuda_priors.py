"""The priors on CUDA: half precision and CUDA-graph replay agree with the CPU/eager results.

Skipped without a GPU (as in CI); the tiny models come from the session fixture.
"""

from __future__ import annotations

import pytest
import torch

from morpheus_core.diffusion import NoiseSchedule
from morpheus_core.guidance import PriorBinding, hybrid_guidance
from morpheus_core.guidance_presets import PRIOR_2D, PRIOR_3D, stage2_texture
from morpheus_core.priors.image2d import Image2DPrior, Image2DSettings
from morpheus_core.priors.lora import ObjectLoras
from morpheus_core.priors.runtime import PriorRuntime
from morpheus_core.priors.zero123 import Zero123Prior
from tests.helpers import RES_2D, photo

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")]

RUNTIMES = [
    PriorRuntime("cuda", torch.float32),
    PriorRuntime("cuda", torch.float32, accel="cudagraph"),
    PriorRuntime("cuda", torch.float16, channels_last=True),
    PriorRuntime("cuda", torch.float16, channels_last=True, accel="cudagraph"),
    PriorRuntime("cuda", torch.bfloat16),
]


@pytest.fixture
def exact_fp32():
    """cuDNN convolutions default to TF32 (~1e-3 relative error): compare fp32 at full precision."""
    old = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    yield
    torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = old


def _close(got: torch.Tensor, want: torch.Tensor, dtype: torch.dtype) -> bool:
    tol = 1e-3 if dtype == torch.float32 else 5e-2
    return bool(torch.isfinite(got).all()) and float((got - want).abs().max()) <= tol * float(want.abs().max())


@pytest.mark.parametrize("runtime", RUNTIMES, ids=lambda r: f"{r.dtype}-{r.accel}")
def test_zero123_on_cuda_matches_cpu(models_root, runtime: PriorRuntime, exact_fp32) -> None:
    folder = models_root / "zero123-xl"
    g = torch.Generator().manual_seed(0)
    zt, t = torch.randn(2, 4, 32, 32, generator=g), torch.tensor([100, 700])
    elev, azim = torch.tensor([10.0, -20.0]), torch.tensor([45.0, 170.0])
    cpu = Zero123Prior.from_folder(folder)
    cpu.set_reference("o", photo(0))
    want = cpu.predict_noise(zt, t, cpu.condition(["o", "o"], elev, azim), 3.0)
    gpu = Zero123Prior.from_folder(folder, runtime)
    gpu.set_reference("o", photo(0))
    for _ in range(3):  # graph capture on the first call, replays after
        got = gpu.predict_noise(zt.cuda(), t.cuda(), gpu.condition(["o", "o"], elev, azim), 3.0)
        assert _close(got.cpu().float(), want, runtime.dtype)


@pytest.mark.parametrize("runtime", RUNTIMES, ids=lambda r: f"{r.dtype}-{r.accel}")
def test_stage2_guidance_step_with_lora_on_cuda(models_root, registry, runtime: PriorRuntime) -> None:
    settings = Image2DSettings(resolution=RES_2D)
    cpu = Image2DPrior.from_registry(registry, settings=settings)
    zero123 = Zero123Prior.from_registry(registry, runtime)
    prior2d = Image2DPrior.from_registry(registry, runtime, settings)
    loras = ObjectLoras(prior2d)
    ids = ["a", "b"]
    for i, oid in enumerate(ids):
        for p in (cpu, zero123, prior2d):
            p.set_reference(oid, photo(i))
        loras.add(oid)
    g = torch.Generator().manual_seed(1)
    renders = torch.rand(2, 3, 64, 64, generator=g)
    zt, t = torch.randn(2, 4, 8, 8, generator=g), torch.tensor([50, 600])
    want = cpu.predict_noise(zt, t, cpu.condition(ids, renders), 2.0)
    got = prior2d.predict_noise(zt.cuda(), t.cuda(), prior2d.condition(ids, renders.cuda()), 2.0)
    assert _close(got.cpu().float(), want, runtime.dtype)
    novel = renders.cuda().requires_grad_(True)
    bindings = {PRIOR_3D: PriorBinding(zero123, condition=zero123.condition(ids, torch.zeros(2), torch.ones(2))),
                PRIOR_2D: PriorBinding(prior2d, loras, prior2d.condition(ids, novel))}
    for step in range(3):
        novel.grad = None
        out = hybrid_guidance(stage2_texture(), bindings, NoiseSchedule(), novel, step,
                              generator=torch.Generator().manual_seed(step))
        (out.loss + out.finetune_loss).backward()
        assert torch.isfinite(novel.grad).all() and novel.grad.abs().sum() > 0
        assert not loras.step().any()
    assert all(p.dtype == torch.float32 for p in loras.parameters("a"))
