"""CUDA agreement with the CPU (skipped where no GPU is present, as in CI)."""

from __future__ import annotations

import pytest
import torch

from morpheus_core.guidance.diffusion import NoiseSchedule
from morpheus_core.guidance.frequency import BandMask, dct2, filter_residual, idct2
from morpheus_core.guidance.hybrid import PriorBinding, TermDraw, hybrid_guidance
from morpheus_core.guidance.presets import PRIOR_2D, PRIOR_3D, stage2_texture
from morpheus_core.priors.proxy.prior import ColourDeviation, LowPass, ProxyPrior, constant_target

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")]


@pytest.fixture
def tf32_on():
    old = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = True
    yield
    torch.backends.cuda.matmul.allow_tf32 = old


@pytest.mark.parametrize("side", [17, 64, 128, 256, 512])
@pytest.mark.parametrize("method", ["matrix", "fft"])
def test_dct_on_cuda_is_exact_even_with_tf32(side: int, method: str, tf32_on) -> None:
    x = torch.randn(2, 3, side, side + 3, generator=torch.Generator().manual_seed(side))
    ref = dct2(x.double(), method)
    u = dct2(x.cuda(), method)
    assert (u.double().cpu() - ref).abs().max() < 1e-4
    assert (idct2(u, method) - x.cuda()).abs().max() < 1e-5
    band = BandMask.high_pass(0.6)
    on_gpu = filter_residual(x.cuda(), band, method).cpu().double()
    assert (on_gpu - filter_residual(x.double(), band)).abs().max() < 1e-4


def test_guidance_on_cuda_matches_cpu(tf32_on) -> None:
    g = torch.Generator().manual_seed(0)
    y = torch.rand(1, 3, 64, 64, generator=g)
    x = torch.rand(2, 3, 64, 64, generator=g)
    draws = [TermDraw(torch.tensor([100, 400]), torch.randn(2, 3, 64, 64, generator=g)) for _ in range(2)]
    config = stage2_texture(mode_2d="sds")
    grads = []
    for device in ("cpu", "cuda"):
        s = NoiseSchedule()
        yd = y.to(device)
        bindings = {PRIOR_3D: PriorBinding(ProxyPrior(constant_target(yd), s, LowPass(0.6))),
                    PRIOR_2D: PriorBinding(ProxyPrior(constant_target(yd), s, ColourDeviation()))}
        xd = x.detach().clone().to(device).requires_grad_(True)
        ref_render = (y + 0.1).detach().to(device).requires_grad_(True)
        dd = [TermDraw(d.t.to(device), d.noise.to(device)) for d in draws]
        out = hybrid_guidance(config, bindings, s, xd, 0, reference_render=ref_render, reference=yd, draws=dd)
        out.loss.backward()
        grads.append((xd.grad.cpu(), ref_render.grad.cpu()))
    for a, b in zip(*grads, strict=True):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-7)


def test_decimating_a_cuda_mesh_keeps_it_on_the_gpu() -> None:
    """The bake stage decimates meshes over the face budget; on CUDA its faces once came back on the CPU."""
    import trimesh

    from morpheus_core.export.uv_bake import cluster_decimate
    from morpheus_core.geometry.mesh import Mesh

    s = trimesh.creation.icosphere(subdivisions=5)
    mesh = Mesh(torch.tensor(s.vertices, dtype=torch.float32).cuda(), torch.tensor(s.faces).cuda())
    small = cluster_decimate(mesh, 2000)
    assert small.vertices.is_cuda and small.faces.is_cuda and 0 < small.num_faces <= 2000
    assert small.face_normals().isfinite().all()


@pytest.mark.parametrize("n", [1000, 37_123])
def test_compiled_hash_grid_matches_eager_forward_and_backward(n: int) -> None:
    """The CUDA path compiles the encode kernels (torch.compile, dynamic shapes); values and both
    gradients must match the eager kernels at any point count."""
    from morpheus_core.geometry.hashgrid import HashGrid, HashGridConfig
    from morpheus_core.runtime.execution import ExecutionConfig, executing

    grid = HashGrid(HashGridConfig(), generator=torch.Generator().manual_seed(n)).cuda()
    with torch.no_grad():
        grid.table.normal_(0, 0.1, generator=torch.Generator(device="cuda").manual_seed(1))
    x = torch.rand(n, 3, generator=torch.Generator().manual_seed(n + 1)).cuda()
    w = torch.randn(n, grid.output_dim, generator=torch.Generator().manual_seed(n + 2)).cuda()

    def run(compile_flag: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        # The tensor code, compiled or not (Triton: its own test).
        with executing(ExecutionConfig(hashgrid="eager", compile=compile_flag)):
            xi = x.clone().requires_grad_(True)
            grid.table.grad = None
            out = grid(xi)
            (out * w).sum().backward()
        return out.detach(), xi.grad, grid.table.grad.clone()

    eager, compiled = run(False), run(True)
    for a, b in zip(eager, compiled, strict=True):
        assert torch.isfinite(b).all()
        assert (a - b).abs().max() <= 1e-4 * max(1.0, float(a.abs().max()))
