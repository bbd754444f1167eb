"""The priors on CUDA: half precision and CUDA-graph replay agree with the CPU/eager results.

Skipped without a GPU (as in CI); the tiny models come from the session fixture.
"""

from __future__ import annotations

import pytest
import torch

from morpheus_core.guidance.diffusion import NoiseSchedule
from morpheus_core.guidance.hybrid import PriorBinding, hybrid_guidance
from morpheus_core.guidance.presets import PRIOR_2D, PRIOR_3D, stage2_texture
from morpheus_core.priors.image2d import Image2DPrior, Image2DSettings
from morpheus_core.priors.lora import ObjectLoras
from morpheus_core.priors.runtime import PriorRuntime
from morpheus_core.priors.zero123 import Zero123Prior
from morpheus_core.runtime.cuda_graphs import GraphedCall
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


def _adapted_pair(registry, loader, ids, dtype):
    """The same prior with the same random adapters twice: eager, and replayed from CUDA graphs."""
    pair = []
    for accel in ("eager", "cudagraph"):
        prior = loader(registry, PriorRuntime("cuda", dtype, accel=accel))
        loras = ObjectLoras(prior)
        for i, oid in enumerate(ids):
            prior.set_reference(oid, photo(i))
            loras.add(oid)
        pair.append((prior, loras))
    for i, oid in enumerate(ids):
        _same_random_adapter(pair, oid, i)
    return pair


def _same_random_adapter(pair, oid: str, seed: int) -> None:
    """B starts at zero (ε_φ = prior) and A at a random init of its own: the same random weights in
    both make the adapters matter and the two paths comparable."""
    g = torch.Generator().manual_seed(seed)
    state = {k: torch.randn(v.shape, generator=g) * 0.05 for k, v in pair[0][1].state_dict(oid).items()}
    for _, loras in pair:
        loras.load_state_dict(oid, state)


def _image2d(registry, runtime):
    return Image2DPrior.from_registry(registry, runtime, Image2DSettings(resolution=RES_2D))


def _zero123(registry, runtime):
    return Zero123Prior.from_registry(registry, runtime)


def _condition(prior, ids, g):
    if isinstance(prior, Image2DPrior):
        return prior.condition(ids, torch.rand(len(ids), 3, RES_2D, RES_2D, generator=g).cuda())
    n = len(ids)
    return prior.condition(ids, torch.rand(n, generator=g) * 40 - 20, torch.rand(n, generator=g) * 360 - 180)


@pytest.mark.parametrize("loader", [_image2d, _zero123], ids=["image2d", "zero123"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float16], ids=str)
def test_graphed_lora_matches_eager_through_adam_steps_and_a_new_object(registry, loader, dtype,
                                                                        exact_fp32) -> None:
    """ε_φ (no grad, CFG) and the fine-tuning loss's adapter gradients replayed from CUDA graphs
    equal the eager hooks' while Adam moves the adapters in place, and after an object joins."""
    pair = _adapted_pair(registry, loader, ["a", "b"], dtype)
    rows = ["a", "b", "a"]
    for step in range(4):
        if step == 3:  # a new object: its adapters are new storage, so the graphs are captured again
            for prior, loras in pair:
                prior.set_reference("c", photo(5))
                loras.add("c")
            _same_random_adapter(pair, "c", 9)
            rows = ["c", "a", "b"]
        g = torch.Generator().manual_seed(100 + step)
        zt = torch.randn(len(rows), 4, *(8, 8) if loader is _image2d else (32, 32), generator=g).cuda()
        t = torch.randint(20, 980, (len(rows),), generator=g).cuda()
        noise = torch.randn(zt.shape, generator=g).cuda()
        results = []
        for prior, loras in pair:
            cond = _condition(prior, rows, torch.Generator().manual_seed(200 + step))
            with torch.no_grad():
                eps_cfg = loras.predict_noise(zt, t, cond, 2.0)
            loss = (loras.predict_noise(zt, t, cond, 1.0) - noise).pow(2).mean()
            loss.backward()
            grads = torch.cat([p.grad.flatten() for oid in loras.object_ids for p in loras.parameters(oid)])
            assert not loras.step().any()
            results.append((eps_cfg, loss.detach(), grads))
            del loss
        (e_eps, e_loss, e_grad), (g_eps, g_loss, g_grad) = results
        for name, got, want in (("eps", g_eps, e_eps), ("loss", g_loss, e_loss), ("grad", g_grad, e_grad)):
            err = float((got.float() - want.float()).abs().max())
            assert _close(got.float(), want.float(), dtype), (step, name, err, float(want.abs().max()))
        assert e_grad.abs().sum() > 0
    graphed = pair[1][1]
    assert len(graphed._graphs) == 2  # the old objects' graphs went with the new object


def test_graphed_call_gradients_match_eager_and_see_in_place_updates() -> None:
    """A small network with a trainable weight (params) and an input that requires grad: replayed
    values and both gradients equal eager autograd's, also after the weight moved in place."""
    g = torch.Generator(device="cuda").manual_seed(3)
    w = torch.randn(16, 8, device="cuda", generator=g).requires_grad_(True)
    frozen = torch.randn(8, 16, device="cuda", generator=g)

    def fn(x: torch.Tensor) -> torch.Tensor:
        return torch.tanh(x @ w.t()) @ frozen.t()

    graphed = GraphedCall(fn, [w])
    for step in range(4):
        x = torch.randn(5, 8, device="cuda", generator=g).requires_grad_(True)
        got = graphed(x)
        got.pow(2).sum().backward()
        x_eager = x.detach().clone().requires_grad_(True)
        want = fn(x_eager)
        want_gx, want_gw = torch.autograd.grad(want.pow(2).sum(), [x_eager, w])
        assert torch.allclose(got, want, atol=1e-5), step
        assert torch.allclose(x.grad, want_gx, atol=1e-5) and torch.allclose(w.grad, want_gw, atol=1e-5), step
        with torch.no_grad():  # an optimiser's in-place step: the next replay must read it
            w -= 0.1 * w.grad
        w.grad = None
        del got, want  # an eager graph through ``w`` alive at a capture made it fail (GraphedCall)
        with torch.no_grad():
            assert torch.allclose(graphed(x), fn(x), atol=1e-5)  # the forward-only graph
    assert len(graphed.graphs) == 2


def test_graphed_call_of_several_outputs_takes_the_gradients_of_those_used() -> None:
    """A tuple of outputs: each is replayed; an output the loss does not use adds no gradient."""
    g = torch.Generator(device="cuda").manual_seed(5)
    w = torch.randn(8, 8, device="cuda", generator=g).requires_grad_(True)

    def fn(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        h = x @ w
        return h.sin(), h.square()[:, :3], h.sum(-1)

    graphed = GraphedCall(fn, [w], keep=1)
    for used in ((0, 1, 2), (1,), (0, 2)):
        x = torch.randn(6, 8, device="cuda", generator=g)
        got = graphed(x)
        sum(got[i].cos().sum() for i in used).backward()
        want = fn(x)
        want_gw = torch.autograd.grad(sum(want[i].cos().sum() for i in used), [w])[0]
        assert all(torch.allclose(a, b, atol=1e-5) for a, b in zip(got, want, strict=True)), used
        assert torch.allclose(w.grad, want_gw, atol=1e-4), used
        w.grad = None
        del got, want
    assert len(graphed.graphs) == 1


def test_graphed_call_refuses_a_backward_after_its_buffers_were_reused() -> None:
    w = torch.randn(4, 4, device="cuda").requires_grad_(True)
    graphed = GraphedCall(lambda x: (x @ w).sin(), [w])
    first = graphed(torch.randn(3, 4, device="cuda"))
    graphed(torch.randn(3, 4, device="cuda"))  # same signature: the first call's activations are overwritten
    with pytest.raises(RuntimeError, match="saved activations are gone"):
        first.sum().backward()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float16], ids=str)
def test_graphed_vae_encode_matches_eager_values_and_gradients(registry, dtype, exact_fp32) -> None:
    eager, graphed = (Image2DPrior.from_registry(registry, PriorRuntime("cuda", dtype, accel=a),
                                                 Image2DSettings(resolution=RES_2D)) for a in ("eager", "cudagraph"))
    graphed.codec.vae.load_state_dict(eager.codec.vae.state_dict())
    g = torch.Generator().manual_seed(4)
    for _ in range(3):
        images = torch.rand(2, 3, RES_2D, RES_2D, generator=g).cuda()
        results = []
        for prior in (eager, graphed):
            x = images.clone().requires_grad_(True)
            z = prior.encode(x)
            (z * torch.linspace(-1, 1, z.numel(), device="cuda").reshape(z.shape)).sum().backward()
            results.append((z.detach(), x.grad))
        (ez, eg), (gz, gg) = results
        vae = eager.codec.vae.dtype
        assert gz.dtype == torch.float32 and _close(gz, ez, vae) and _close(gg, eg, vae)


def test_graphed_call_recaptures_an_evicted_signature_correctly() -> None:
    w = torch.randn(6, 6, device="cuda").requires_grad_(True)
    graphed = GraphedCall(lambda x: torch.relu(x @ w), [w], keep=1)
    for rows in (2, 3, 2, 3):  # every call evicts the other signature's graphs
        x = torch.randn(rows, 6, device="cuda")
        y = graphed(x)
        y.sum().backward()
        want = torch.autograd.grad(torch.relu(x @ w).sum(), [w])[0]
        assert torch.allclose(w.grad, want, atol=1e-5) and len(graphed.graphs) == 1
        w.grad = None
        del y


def test_released_graphs_give_their_memory_back_and_are_captured_again_when_called() -> None:
    from morpheus_core.runtime.cuda_graphs import release_graphs

    w = torch.randn(256, 256, device="cuda").requires_grad_(True)
    graphed = GraphedCall(lambda x: torch.tanh(x @ w) @ w, [w])
    x = torch.randn(4096, 256, device="cuda")
    graphed(x).sum().backward()
    torch.cuda.synchronize()
    held = torch.cuda.memory_reserved()
    release_graphs()
    assert len(graphed.graphs) == 0 and torch.cuda.memory_reserved() < held
    w.grad = None
    before = GraphedCall.captures
    graphed(x).sum().backward()
    want = torch.autograd.grad((torch.tanh(x @ w) @ w).sum(), [w])[0]
    assert GraphedCall.captures == before + 1 and torch.allclose(w.grad, want, rtol=1e-4, atol=1e-4)
