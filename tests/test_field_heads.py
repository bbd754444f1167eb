"""Fused field-head kernels (``mlp_triton``) against the ``nn.Sequential`` heads they replace.

Without CUDA the kernels run under Triton's CPU interpreter (set before ``mlp_triton`` is
imported, as in ``test_hashgrid_triton``); with CUDA the same tests run the compiled kernels, whose
TF32 tensor-core products are compared with a looser tolerance.
"""

from __future__ import annotations

import os

import pytest
import torch
from torch import nn

from morpheus_core.geometry.field_heads import evaluate_heads, head_parameters
from morpheus_core.geometry.hashgrid import HashGridConfig
from morpheus_core.geometry.nerf import NerfConfig, NerfField, head_mlp
from morpheus_core.runtime.execution import ExecutionConfig, executing

CUDA = torch.cuda.is_available()
if not CUDA:
    os.environ["TRITON_INTERPRET"] = "1"
pytest.importorskip("triton")

from morpheus_core.geometry import mlp_triton  # noqa: E402  (after TRITON_INTERPRET)

DEVICE = torch.device("cuda" if CUDA else "cpu")
REL = 5e-3 if CUDA else 2e-6  # CUDA: TF32 products


def heads(n_in: int, hidden: int, n_out: int, seed: int) -> tuple[nn.Sequential, nn.Sequential]:
    torch.manual_seed(seed)
    return head_mlp(n_in, hidden, 2, 1).to(DEVICE), head_mlp(n_in, hidden, 2, n_out).to(DEVICE)


def problem(n: int, n_in: int, hidden: int, grad_width: int,
            seed: int) -> tuple[list, list, torch.Tensor, torch.Tensor]:
    """Both heads' parameters, features (n, n_in) and an upstream gradient (n, grad_width)."""
    density, albedo = heads(n_in, hidden, 3, seed=seed)
    g = torch.Generator().manual_seed(seed + 1)
    x = torch.randn(n, n_in, generator=g).to(DEVICE)
    grad = torch.randn(n, grad_width, generator=g).to(DEVICE)
    return head_parameters(density), head_parameters(albedo), x, grad


def assert_near(got: torch.Tensor | None, want: torch.Tensor | None, rel: float = REL) -> None:
    assert got is not None and want is not None
    got, want = got.detach(), want.detach()
    assert got.shape == want.shape and got.dtype == want.dtype
    err = float((got.double() - want.double()).abs().max()) if got.numel() else 0.0
    scale = max(1.0, float(want.abs().max())) if want.numel() else 1.0
    assert err <= rel * scale, f"max abs error {err:.3g} > {rel:g} × {scale:.3g}"


def firm_relus(mlp: nn.Sequential, x: torch.Tensor, g: torch.Generator) -> None:
    """Shift the hidden biases so that every pre-activation is at least its unit's largest |value|
    away from 0, on or off at random per unit. TF32 products move a pre-activation by ~1e-3 of
    its size; one near 0 could then switch its ReLU in the kernel but not in the fp32 modules and
    change the gradient by a whole unit's share, which no tolerance on the products would cover."""
    h = x.detach()
    with torch.no_grad():
        for layer in list(mlp)[:-1]:
            if isinstance(layer, nn.Linear):
                pre = layer(h)
                sign = torch.randint(0, 2, (layer.out_features,), generator=g).to(h.device) * 2.0 - 1.0
                layer.bias += sign * 2.0 * pre.abs().amax(0)
            h = layer(h)


@pytest.mark.parametrize(("n", "n_in", "hidden", "n_out"),
                         [(300, 32, 64, 3), (129, 12, 20, 3), (70, 32, 64, 1), (1, 5, 17, 16), (0, 32, 64, 3)])
def test_kernels_match_the_modules(n: int, n_in: int, hidden: int, n_out: int) -> None:
    """Odd widths (padded, masked), a row count off the block size, one row, no rows."""
    density, albedo = heads(n_in, hidden, n_out, seed=n + n_in)
    g = torch.Generator().manual_seed(n)
    x = (torch.randn(n, n_in, generator=g) * 2).to(DEVICE).requires_grad_()
    if CUDA and n:
        firm_relus(density, x, g)
        firm_relus(albedo, x, g)
    ref_d, ref_a = density(x), albedo(x)
    grad_d = torch.randn(ref_d.shape, generator=g).to(DEVICE)
    grad_a = torch.randn(ref_a.shape, generator=g).to(DEVICE)
    torch.autograd.backward([ref_d, ref_a], [grad_d, grad_a])
    pd, pa = head_parameters(density), head_parameters(albedo)
    out_d, out_a = mlp_triton.heads_forward(x.detach(), pd, pa)
    assert_near(out_d, ref_d.detach())
    assert_near(out_a, ref_a.detach())
    grad_x, grads_d, grads_a = mlp_triton.heads_backward(x.detach(), pd, pa, grad_d, grad_a, True)
    assert_near(grad_x, x.grad)
    for got, p in zip([*grads_d, *grads_a], [*pd, *pa], strict=True):
        assert_near(got, p.grad)
    if n:
        assert float(grad_x.abs().sum()) > 0 and all(float(p.grad.abs().sum()) > 0 for p in pd[:2])


@pytest.mark.skipif(CUDA, reason="TF32 rounding on CUDA swamps the differences; the CPU interpreter computes in fp32")
def test_gradients_match_finite_differences() -> None:
    """Central differences of the kernels' own forward (fp32, so a loose tolerance)."""
    pd, pa, x, grad_a = problem(40, 8, 16, 3, seed=3)
    _, _, grads_a = mlp_triton.heads_backward(x, pd, pa, None, grad_a, False)
    w2 = pa[2]
    eps = 1e-2
    for idx in [(0, 0), (3, 7), (15, 15)]:
        with torch.no_grad():
            old = float(w2[idx])
            w2[idx] = old + eps
            up = float((mlp_triton.heads_forward(x, pd, pa)[1] * grad_a).double().sum())
            w2[idx] = old - eps
            down = float((mlp_triton.heads_forward(x, pd, pa)[1] * grad_a).double().sum())
            w2[idx] = old
        assert abs((up - down) / (2 * eps) - float(grads_a[2][idx])) < 2e-2 * max(1.0, abs(float(grads_a[2][idx])))


def test_backward_is_deterministic_and_skips_unused_heads() -> None:
    pd, pa, x, grad_d = problem(500, 32, 64, 1, seed=5)
    first = mlp_triton.heads_backward(x, pd, pa, grad_d, None, True)
    second = mlp_triton.heads_backward(x, pd, pa, grad_d, None, True)
    assert first[2] is None and second[2] is None  # no albedo gradient: that head is not run
    assert torch.equal(first[0], second[0])
    assert all(torch.equal(a, b) for a, b in zip(first[1], second[1], strict=True))
    none = mlp_triton.heads_backward(x, pd, pa, None, None, True)
    assert none == (None, None, None)
    with pytest.raises(ValueError, match="albedo gradient without an albedo head"):
        mlp_triton.heads_backward(x, pd, None, grad_d, torch.ones(500, 3, device=DEVICE), True)


@pytest.mark.parametrize("n", [203, 64, 1, 0])
def test_weight_gradient_modes_agree(n: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """Matmuls over the stored activations (``gemm``) and per-program partials (``fused``) give the
    same gradients, with both heads, either alone, with and without the feature gradient."""
    pd, pa, x, grad_d = problem(n, 32, 64, 1, seed=13)
    grad_a = torch.randn(n, 3, generator=torch.Generator().manual_seed(14)).to(DEVICE)
    for gd, ga, want_x in [(grad_d, grad_a, True), (grad_d, None, True), (None, grad_a, True),
                           (grad_d, grad_a, False)]:
        monkeypatch.setattr(mlp_triton, "_WEIGHT_GRADS", "fused")
        want = mlp_triton.heads_backward(x, pd, pa, gd, ga, want_x)
        monkeypatch.setattr(mlp_triton, "_WEIGHT_GRADS", "gemm")
        got = mlp_triton.heads_backward(x, pd, pa, gd, ga, want_x)
        assert (got[0] is None) == (not want_x)
        if want_x:
            assert_near(got[0], want[0], rel=1e-5)
        for got_head, want_head in zip(got[1:], want[1:], strict=True):
            assert (got_head is None) == (want_head is None)
            for a, b in zip(got_head or [], want_head or [], strict=True):
                assert_near(a, b, rel=REL if CUDA else 1e-4)  # CUDA: TF32 products against the matmuls
        if n:
            assert all(float(g.abs().sum()) > 0 for g in (got[1] or got[2])[:2])


@pytest.mark.parametrize("mode", ["store", "relaxed"])
def test_feature_gradient_modes_agree(mode: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Each way the fused weight gradients' heads meet in the feature gradient gives the reference's
    (acq_rel atomics) result, with both heads, with either alone, and with a row count off the block size."""
    monkeypatch.setattr(mlp_triton, "_WEIGHT_GRADS", "fused")
    pd, pa, x, grad_d = problem(203, 32, 64, 1, seed=11)
    grad_a = torch.randn(203, 3, generator=torch.Generator().manual_seed(12)).to(DEVICE)
    for gd, ga in [(grad_d, grad_a), (grad_d, None), (None, grad_a)]:
        monkeypatch.setattr(mlp_triton, "_GRAD_X", "acq_rel")
        want = mlp_triton.heads_backward(x, pd, pa, gd, ga, True)
        monkeypatch.setattr(mlp_triton, "_GRAD_X", mode)
        got = mlp_triton.heads_backward(x, pd, pa, gd, ga, True)
        assert_near(got[0], want[0], rel=1e-5)
        assert float(got[0].abs().sum()) > 0
        for got_head, want_head in zip(got[1:], want[1:], strict=True):
            assert (got_head is None) == (want_head is None)
            for a, b in zip(got_head or [], want_head or [], strict=True):
                assert torch.equal(a, b)  # the parameter partials do not depend on the mode


def test_unsupported_inputs() -> None:
    density, albedo = heads(32, 64, 3, seed=7)
    x = torch.randn(10, 32, device=DEVICE)
    pd, pa = head_parameters(density), head_parameters(albedo)
    assert mlp_triton.supports(x, [pd, pa])
    assert not mlp_triton.supports(x.double(), [pd, pa])
    assert not mlp_triton.supports(torch.randn(10, 200, device=DEVICE), [pd])
    _, wide_out = heads(32, 64, 17, seed=8)
    assert not mlp_triton.supports(x, [pd, head_parameters(wide_out)])
    _, other_width = heads(32, 48, 3, seed=9)
    assert not mlp_triton.supports(x, [pd, head_parameters(other_width)])  # the heads share one width
    assert head_parameters(head_mlp(32, 64, 1, 1)) is None  # one hidden layer: the modules run it
    with pytest.raises(ValueError, match="fused field heads take fp32"):
        mlp_triton.heads_forward(x.double(), pd, pa)


def small_field(seed: int) -> NerfField:
    cfg = NerfConfig(grid=HashGridConfig(n_levels=4, log2_table_size=10, base_resolution=4, per_level_scale=1.5),
                     hidden=32)
    return NerfField(cfg, generator=torch.Generator().manual_seed(seed)).to(DEVICE)


def field_grads(field: NerfField, points: torch.Tensor, choice: str,
                albedo_only: bool = False) -> tuple[list[torch.Tensor], dict[str, torch.Tensor | None]]:
    field.zero_grad(set_to_none=True)
    with executing(ExecutionConfig(field_mlp=choice)):  # type: ignore[arg-type]
        sample = field.query(points)
        loss = (sample.albedo * torch.linspace(-1, 1, 3, device=DEVICE)).sum()
        if not albedo_only:
            loss = loss + (sample.density.log1p() * points[:, 0]).sum() + field.density(points * 0.5).sum()
        loss.backward()
    return [sample.density.detach(), sample.albedo.detach()], {n: p.grad for n, p in field.named_parameters()}


@pytest.mark.parametrize("albedo_only", [False, True])
def test_field_query_and_gradients_match_eager(monkeypatch: pytest.MonkeyPatch, albedo_only: bool) -> None:
    """Through ``NerfField``: the hash table's gradient passes the kernels' feature gradient on."""
    field = small_field(10)
    points = (torch.rand(257, 3, generator=torch.Generator().manual_seed(11)) * 1.6 - 0.8).to(DEVICE)
    want_out, want_grads = field_grads(field, points, "eager", albedo_only)
    launches = []
    backward = mlp_triton.heads_backward
    monkeypatch.setattr(mlp_triton, "heads_backward",
                        lambda *a: launches.append((a[3] is not None, a[4] is not None)) or backward(*a))
    got_out, got_grads = field_grads(field, points, "triton", albedo_only)
    # The kernels ran, in reverse order of the forward: (density wanted, albedo wanted) per call.
    assert launches == ([(False, True)] if albedo_only else [(True, False), (True, True)])
    for got, want in zip(got_out, want_out, strict=True):
        assert_near(got, want, 5e-3 if CUDA else 1e-5)
    assert got_grads.keys() == want_grads.keys()
    for name, want in want_grads.items():
        if want is None:  # the density head under an albedo-only loss
            assert got_grads[name] is None, name
        else:
            assert_near(got_grads[name], want, 5e-3 if CUDA else 1e-5)
    assert albedo_only == (want_grads["density_mlp.0.weight"] is None)


def test_backend_choice(monkeypatch: pytest.MonkeyPatch) -> None:
    """``execution.field_mlp`` (``morpheus_core.runtime.execution``) picks the path, not the environment."""
    density, albedo = heads(32, 64, 3, seed=30)
    x = torch.randn(20, 32, device=DEVICE)
    with pytest.raises(ValueError, match=r"execution\.field_mlp must be one of auto, triton, eager"):
        ExecutionConfig(field_mlp="fast")  # type: ignore[arg-type]
    one_layer = head_mlp(32, 64, 1, 3).to(DEVICE)  # not a shape the kernels take: the module, under any choice
    with executing(ExecutionConfig(field_mlp="triton")):
        assert_near(evaluate_heads(x, density, one_layer)[1], one_layer(x), 0.0)

    def refuse(*args, **kwargs):
        raise AssertionError("a Triton kernel ran on the eager path")

    monkeypatch.setattr(mlp_triton, "heads_forward", refuse)
    with executing(ExecutionConfig(field_mlp="eager")):
        assert_near(evaluate_heads(x, density, albedo)[0], density(x), 0.0)
    with executing(ExecutionConfig()):  # auto: the kernels on CUDA, the modules on the CPU
        if CUDA:
            with pytest.raises(AssertionError, match="a Triton kernel ran"):
                evaluate_heads(x, density, albedo)
        else:
            assert_near(evaluate_heads(x, density, albedo)[1], albedo(x), 0.0)
    if not CUDA:
        monkeypatch.setenv("TRITON_INTERPRET", "0")
        with executing(ExecutionConfig(field_mlp="triton")), pytest.raises(
                RuntimeError, match=r"execution\.field_mlp=triton but the Triton field-MLP kernels cannot run"):
            evaluate_heads(x, density, albedo)
