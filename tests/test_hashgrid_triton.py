"""Triton hash-grid kernels against the eager encoder (``eager_encode_forward`` / ``eager_encode_backward``).

Without CUDA the kernels run under Triton's CPU interpreter. Triton reads ``TRITON_INTERPRET``
when ``@triton.jit`` runs — when ``hashgrid_triton`` is imported — so it is set before that import.
With CUDA the same tests run the compiled kernels on the GPU.
"""

from __future__ import annotations

import os

import pytest
import torch

from morpheus_core.geometry.hashgrid import (
    HashGrid,
    HashGridConfig,
    LevelTables,
    eager_encode_backward,
    eager_encode_forward,
    triton_kernels,
)
from morpheus_core.runtime.execution import ExecutionConfig, apply_execution, executing

CUDA = torch.cuda.is_available()
if not CUDA:
    os.environ["TRITON_INTERPRET"] = "1"
pytest.importorskip("triton")

from morpheus_core.geometry import hashgrid_triton  # noqa: E402  (after TRITON_INTERPRET)

DEVICE = torch.device("cuda" if CUDA else "cpu")


def mixed(features: int) -> HashGridConfig:
    """Levels of resolution 2, 4, 6 stored densely (8, 64, 216 rows), 9 and 14 hashed (256 rows)."""
    return HashGridConfig(n_levels=5, n_features_per_level=features, log2_table_size=8, base_resolution=2,
                          per_level_scale=1.6)


def integer_scales(features: int) -> HashGridConfig:
    """Scales 1, 3, 7, 15 (res 2, 4, 8, 16): x = 1 puts the upper corner one past the grid, where it wraps."""
    return HashGridConfig(n_levels=4, n_features_per_level=features, log2_table_size=7, base_resolution=2,
                          per_level_scale=2.0)


SPECIAL = [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [1.0, 0.0, 0.5], [0.0, 1.0, 1.0], [0.5, 0.5, 0.5], [0.25, 1.0, 0.0]]


def inputs(config: HashGridConfig, n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, LevelTables]:
    g = torch.Generator().manual_seed(seed)
    tables = LevelTables(config, DEVICE)
    table = torch.randn(int(tables.rows.sum()), config.n_features_per_level, generator=g)
    x = torch.rand(n, 3, generator=g)
    x[: len(SPECIAL)] = torch.tensor(SPECIAL)
    return x.to(DEVICE), table.to(DEVICE), tables


def assert_near(got: torch.Tensor | None, want: torch.Tensor | None, rel: float) -> None:
    assert got is not None and want is not None
    assert got.shape == want.shape and got.dtype == want.dtype and got.device == want.device
    err = float((got.double() - want.double()).abs().max()) if got.numel() else 0.0
    scale = max(1.0, float(want.abs().max())) if want.numel() else 1.0
    assert err <= rel * scale, f"max abs error {err:.3g} > {rel:g} × {scale:.3g}"


def compare(config: HashGridConfig, level_mask: torch.Tensor, n: int = 160, seed: int = 0, objects: int = 1) -> None:
    """Kernels against the eager code; ``objects`` > 1: that many tables one after another, each point
    reading the table of a random object (the kernels' row bases)."""
    x, table, tables = inputs(config, n, seed)
    base = None
    if objects > 1:
        g = torch.Generator().manual_seed(seed + 2)
        table = torch.cat([table] + [torch.randn(table.shape, generator=g).to(DEVICE) for _ in range(objects - 1)])
        base = (torch.randint(0, objects, (n,), generator=g) * (table.shape[0] // objects)).to(DEVICE)
    mask = level_mask.to(DEVICE)
    ref = eager_encode_forward(x, table, tables, mask, base)
    out = hashgrid_triton.encode_forward(x, table, tables, mask, base)
    assert_near(out, ref, 2e-6)
    grad_out = torch.randn(ref.shape, generator=torch.Generator().manual_seed(seed + 1)).to(DEVICE)
    want_gx, want_gt = eager_encode_backward(x, table, tables, mask, grad_out, True, True, base)
    got_gx, got_gt = hashgrid_triton.encode_backward(x, table, tables, mask, grad_out, True, True, base)
    assert_near(got_gx, want_gx, 2e-6)
    assert_near(got_gt, want_gt, 2e-6)
    # The table-only backward runs another grid (one level per program): the same gradient.
    none_x, only_gt = hashgrid_triton.encode_backward(x, table, tables, mask, grad_out, False, True, base)
    assert none_x is None
    assert_near(only_gt, want_gt, 2e-6)
    if base is not None:  # every object's table got gradient from its own points only
        rows = table.shape[0] // objects
        for k in range(objects):
            assert (got_gt[k * rows:(k + 1) * rows].abs().sum() > 0) == bool((base == k * rows).any())


def test_stacked_objects_match_eager() -> None:
    compare(mixed(2), torch.ones(5), n=300, seed=3, objects=3)
    compare(integer_scales(4), (torch.arange(4) < 3).float(), n=200, seed=4, objects=2)


def clustered(config: HashGridConfig, n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, LevelTables]:
    """Points in runs that share cells, as the NeRF stage's samples come: sorted along x (neighbours
    close), runs of one repeated point (one across the 128-lane block edge, one up to the last point,
    in the cell at the origin, where the kernel's masked loads past the end also land)."""
    x, table, tables = inputs(config, n, seed)
    x = x[torch.argsort(x[:, 0])]
    x[n - 20:] = 0.01
    for start, stop in ((5, 40), (110, 150)):
        x[start:stop] = x[start]
    return x, table, tables


@pytest.mark.parametrize("mode", ["none", "dense", "all"])
def test_run_reduction_matches_eager_on_clustered_points(mode: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Every ``RUN_REDUCTION``: runs summed before the atomics give eager's table gradient, also where a
    run of one cell holds points of two objects (their rows differ: the run must split there)."""
    monkeypatch.setattr(hashgrid_triton, "RUN_REDUCTION", mode)
    config = mixed(2)
    n, objects = 290, 2
    x, table, tables = clustered(config, n, 20)
    table = torch.cat([table, torch.randn(table.shape, generator=torch.Generator().manual_seed(21)).to(DEVICE)])
    base = ((torch.arange(n) // 7) % objects * (table.shape[0] // objects)).to(DEVICE)  # switches inside runs
    mask = (torch.arange(config.n_levels) < 4).float().to(DEVICE)
    grad_out = torch.randn(n, config.output_dim, generator=torch.Generator().manual_seed(22)).to(DEVICE)
    want_gx, want_gt = eager_encode_backward(x, table, tables, mask, grad_out, True, True, base)
    got_gx, got_gt = hashgrid_triton.encode_backward(x, table, tables, mask, grad_out, True, True, base)
    assert_near(got_gx, want_gx, 2e-6)
    assert_near(got_gt, want_gt, 2e-6)
    _, only_gt = hashgrid_triton.encode_backward(x, table, tables, mask, grad_out, False, True)
    assert_near(only_gt, eager_encode_backward(x, table, tables, mask, grad_out, False, True)[1], 2e-6)


def test_unknown_run_reduction_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(hashgrid_triton, "RUN_REDUCTION", "dens")
    x, table, tables = inputs(mixed(2), 8, 23)
    mask = torch.ones(5, device=DEVICE)
    with pytest.raises(ValueError, match="RUN_REDUCTION"):
        hashgrid_triton.encode_backward(x, table, tables, mask, torch.ones(8, 10, device=DEVICE), False, True)


@pytest.mark.parametrize(("make", "features"), [(mixed, 2), (mixed, 4), (integer_scales, 2), (integer_scales, 4),
                                                (mixed, 1), (integer_scales, 8)])
def test_forward_and_gradients_match_eager(make, features: int) -> None:
    config = make(features)
    tables = LevelTables(config, DEVICE)
    assert 0 < tables.n_dense < config.n_levels  # both kinds of level occur
    compare(config, torch.ones(config.n_levels), seed=features)


def test_unit_cube_corners_wrap_like_eager() -> None:
    """x = 0 and x = 1 on every axis: at integer scales the upper corner of x = 1 lies past the grid."""
    config = integer_scales(2)
    tables = LevelTables(config, DEVICE)
    corners = torch.tensor([[(c >> d) & 1 for d in range(3)] for c in range(8)], dtype=torch.float32)
    g = torch.Generator().manual_seed(5)
    table = torch.randn(int(tables.rows.sum()), 2, generator=g).to(DEVICE)
    mask = torch.ones(config.n_levels, device=DEVICE)
    x = corners.to(DEVICE)
    features = eager_encode_forward(x, table, tables, mask)
    assert_near(hashgrid_triton.encode_forward(x, table, tables, mask), features, 1e-6)
    grad_out = torch.randn(8, config.output_dim, generator=g).to(DEVICE)
    got = hashgrid_triton.encode_backward(x, table, tables, mask, grad_out, True, True)
    want = eager_encode_backward(x, table, tables, mask, grad_out, True, True)
    for a, b in zip(got, want, strict=True):
        assert_near(a, b, 1e-6)


def test_masked_levels_are_zero_and_get_no_gradient() -> None:
    config = mixed(2)
    active = 3
    mask = (torch.arange(config.n_levels) < active).float()
    compare(config, mask, seed=7)
    x, table, tables = inputs(config, 100, 8)
    mask = mask.to(DEVICE)
    out = hashgrid_triton.encode_forward(x, table, tables, mask)
    assert torch.all(out[:, active * 2:] == 0) and torch.all(out[:, : active * 2] != 0)
    _, grad_table = hashgrid_triton.encode_backward(x, table, tables, mask, torch.ones_like(out), False, True)
    first_off = int(tables.offsets[active])
    assert torch.all(grad_table[first_off:] == 0) and grad_table[:first_off].abs().sum() > 0


@pytest.mark.parametrize(("want_x", "want_table"), [(True, False), (False, True), (False, False)])
def test_unwanted_gradients_are_none(want_x: bool, want_table: bool) -> None:
    config = mixed(2)
    x, table, tables = inputs(config, 64, 9)
    mask = torch.ones(config.n_levels, device=DEVICE)
    grad_out = torch.randn(64, config.output_dim, generator=torch.Generator().manual_seed(10)).to(DEVICE)
    got = hashgrid_triton.encode_backward(x, table, tables, mask, grad_out, want_x, want_table)
    want = eager_encode_backward(x, table, tables, mask, grad_out, want_x, want_table)
    for a, b, wanted in zip(got, want, (want_x, want_table), strict=True):
        if wanted:
            assert_near(a, b, 2e-6)
        else:
            assert a is None and b is None


def test_half_precision_table_is_upcast() -> None:
    config = mixed(2)
    x, table, tables = inputs(config, 64, 11)
    mask = torch.ones(config.n_levels, device=DEVICE)
    half = table.to(torch.float16)
    out = hashgrid_triton.encode_forward(x, half, tables, mask)
    assert out.dtype == torch.float16
    assert_near(out.float(), eager_encode_forward(x, half.float(), tables, mask), 2e-3)
    _, grad_table = hashgrid_triton.encode_backward(x, half, tables, mask, torch.ones_like(out), False, True)
    assert grad_table is not None and grad_table.dtype == torch.float16


def test_cpu_keeps_the_eager_path(monkeypatch: pytest.MonkeyPatch) -> None:
    """On the CPU ``auto`` (the default) and ``eager`` never launch a Triton kernel, interpreter or not."""
    x = torch.rand(50, 3)
    grid = HashGrid(mixed(2), generator=torch.Generator().manual_seed(12))

    def refuse(*args, **kwargs):
        raise AssertionError("a Triton kernel ran on the CPU path")

    monkeypatch.setattr(hashgrid_triton, "encode_forward", refuse)
    monkeypatch.setattr(hashgrid_triton, "encode_backward", refuse)
    for choice in ("auto", "eager"):
        with executing(ExecutionConfig(hashgrid=choice)):  # type: ignore[arg-type]
            assert triton_kernels(x, grid.table) is None
            xi = x.clone().requires_grad_(True)
            grid(xi).sum().backward()
            assert xi.grad is not None and grid.table.grad is not None


def test_forcing_triton_where_it_cannot_run_names_the_setting(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TRITON_INTERPRET", "0")
    grid = HashGrid(mixed(2))
    with executing(ExecutionConfig(hashgrid="triton")):
        with pytest.raises(RuntimeError, match=r"execution\.hashgrid=triton"):
            grid(torch.rand(10, 3))
        # float64 (gradcheck) is not the kernels' business: the tensor code runs under either choice.
        assert triton_kernels(torch.rand(10, 3, dtype=torch.float64), grid.table.double()) is None


@pytest.mark.skipif(CUDA, reason="the interpreter path is the CPU's")
def test_forced_triton_through_hash_grid_module_under_the_interpreter() -> None:
    """``execution.hashgrid=triton`` with the interpreter: ``HashGrid`` forward and autograd backward match eager."""
    grid = HashGrid(mixed(2), generator=torch.Generator().manual_seed(13))
    with torch.no_grad():
        grid.table.normal_(generator=torch.Generator().manual_seed(14))
    grid.set_active_levels(4)
    x = torch.rand(100, 3, generator=torch.Generator().manual_seed(15))
    w = torch.randn(100, grid.output_dim, generator=torch.Generator().manual_seed(16))

    def run(choice: str) -> tuple[torch.Tensor, ...]:
        with executing(ExecutionConfig(hashgrid=choice)):  # type: ignore[arg-type]
            xi = x.clone().requires_grad_(True)
            grid.table.grad = None
            out = grid(xi)
            (out * w).sum().backward()
        return out.detach(), xi.grad, grid.table.grad.clone()

    with executing(ExecutionConfig(hashgrid="triton")):
        assert triton_kernels(x, grid.table) is hashgrid_triton
    for got, want in zip(run("triton"), run("eager"), strict=True):
        assert_near(got, want, 2e-6)


@pytest.mark.skipif(CUDA, reason="the interpreter path is the CPU's")
def test_applied_execution_settings_pick_the_hash_grid_path(monkeypatch: pytest.MonkeyPatch) -> None:
    """What ``apply_execution`` (a run's start-up) sets is what the encode reads on its next call;
    the environment alias no longer matters once settings are applied."""
    launches: list[int] = []
    forward = hashgrid_triton.encode_forward
    monkeypatch.setattr(hashgrid_triton, "encode_forward", lambda *a: launches.append(len(a[0])) or forward(*a))
    grid = HashGrid(mixed(2), generator=torch.Generator().manual_seed(17))
    x = torch.rand(30, 3, generator=torch.Generator().manual_seed(18))
    previous = apply_execution(ExecutionConfig(hashgrid="triton"))
    try:
        monkeypatch.setenv("MORPHEUS_HASHGRID", "eager")
        grid(x)
        assert launches == [30]
        apply_execution(ExecutionConfig(hashgrid="eager"))
        grid(x)
        assert launches == [30]
    finally:
        apply_execution(previous)


@pytest.mark.gpu
@pytest.mark.skipif(not CUDA, reason="needs CUDA")
@pytest.mark.parametrize("n", [1000, 37_123])
def test_paper_grid_on_cuda_defaults_to_triton_and_matches_eager(n: int) -> None:
    grid = HashGrid(HashGridConfig(), generator=torch.Generator().manual_seed(n)).cuda()
    with torch.no_grad():
        grid.table.normal_(0, 0.1, generator=torch.Generator(device="cuda").manual_seed(1))
    x = torch.rand(n, 3, generator=torch.Generator().manual_seed(n + 1)).cuda()
    w = torch.randn(n, grid.output_dim, generator=torch.Generator().manual_seed(n + 2)).cuda()
    with executing(ExecutionConfig()):
        assert triton_kernels(x, grid.table) is hashgrid_triton

    def run(choice: str) -> tuple[torch.Tensor, ...]:
        with executing(ExecutionConfig(hashgrid=choice, compile=False)):  # type: ignore[arg-type]
            xi = x.clone().requires_grad_(True)
            grid.table.grad = None
            out = grid(xi)
            (out * w).sum().backward()
        return out.detach(), xi.grad, grid.table.grad.clone()

    for got, want in zip(run("auto"), run("eager"), strict=True):
        assert_near(got, want, 1e-5)
