"""Hash grid: equal to a per-point, per-level reference written from tcnn's formulas; gradients."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch.func import functional_call

from morpheus_core.geometry.hashgrid import HashGrid, HashGridConfig

TINY = HashGridConfig(n_levels=4, n_features_per_level=2, log2_table_size=7, base_resolution=2, per_level_scale=2.0)
# Levels 0-1 dense (res 2, 4), levels 2-3 hashed (res 8 → 512 > 128, res 16).


def reference_encode(x: np.ndarray, table: np.ndarray, cfg: HashGridConfig, active: int) -> np.ndarray:
    """Plain loops over points, levels and the 8 corners, straight from the tcnn definitions."""
    feats = np.zeros((x.shape[0], cfg.n_levels, cfg.n_features_per_level))
    offset = 0
    for level in range(cfg.n_levels):
        scale = cfg.base_resolution * cfg.per_level_scale**level - 1.0
        res = math.ceil(scale) + 1
        size = min(((res**3 + 7) // 8) * 8, 2**cfg.log2_table_size)
        use_hash = ((res**3 + 7) // 8) * 8 > 2**cfg.log2_table_size
        for p, point in enumerate(np.clip(x, 0, 1)):
            pos = point.astype(np.float32) * np.float32(scale) + np.float32(0.5)
            cell = np.floor(pos).astype(np.int64)
            frac = pos - cell
            for corner in range(8):
                c = cell + np.array([(corner >> d) & 1 for d in range(3)])
                w = np.prod([frac[d] if (corner >> d) & 1 else 1 - frac[d] for d in range(3)])
                if use_hash:
                    h = (int(c[0]) * 1) ^ (int(c[1]) * 2654435761 % 2**32) ^ (int(c[2]) * 805459861 % 2**32)
                    row = h % size
                else:
                    row = (int(c[0]) + int(c[1]) * res + int(c[2]) * res * res) % size
                if level < active:
                    feats[p, level] += w * table[offset + row]
        offset += size
    return feats.reshape(x.shape[0], -1)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("active", [4, 2])
def test_matches_reference(seed: int, active: int, device: torch.device) -> None:
    g = torch.Generator().manual_seed(seed)
    grid = HashGrid(TINY, generator=g)
    with torch.no_grad():
        grid.table.normal_(generator=g)
    grid.set_active_levels(active)
    x = torch.rand(200, 3, generator=g)
    x[:5] = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [1.0, 0.0, 0.5], [0.5, 0.5, 0.5], [-0.2, 1.3, 0.1]])
    out = grid.to(device)(x.to(device)).cpu()
    ref = reference_encode(x.numpy(), grid.table.detach().cpu().numpy(), TINY, active)
    np.testing.assert_allclose(out.detach().numpy(), ref, rtol=1e-5, atol=1e-5)


def test_layout_follows_tcnn_conventions() -> None:
    layout = HashGridConfig().level_layout()
    scale0, res0, rows0, hashed0 = layout[0]
    assert (scale0, res0, rows0, hashed0) == (15.0, 16, 16**3, False)
    assert all(rows <= 2**19 for _, _, rows, _ in layout)
    assert layout[-1][3] and layout[-1][1] == math.ceil(16 * 1.447269237440378**15 - 1) + 1


def test_gradcheck_table_and_inputs() -> None:
    g = torch.Generator().manual_seed(3)
    grid = HashGrid(TINY, generator=g).double()
    with torch.no_grad():
        grid.table.normal_(generator=g)
    x = (0.05 + 0.9 * torch.rand(12, 3, generator=g, dtype=torch.float64)).requires_grad_(True)
    # The module's own forward with the table passed in: gradcheck sees both inputs of the hand-written backward.
    assert torch.autograd.gradcheck(lambda pts, tab: functional_call(grid, {"table": tab}, (pts,)), (x, grid.table),
                                    eps=1e-6)


def test_inactive_levels_get_no_gradient_and_zero_features(device: torch.device) -> None:
    grid = HashGrid(TINY, generator=torch.Generator().manual_seed(4)).to(device)
    grid.set_active_levels(2)
    x = torch.rand(64, 3, generator=torch.Generator().manual_seed(5)).to(device)
    out = grid(x)
    assert torch.all(out[:, 4:] == 0)
    out.square().sum().backward()
    layout = TINY.level_layout()
    first_hashed_row = layout[0][2] + layout[1][2]
    assert grid.table.grad[first_hashed_row:].abs().max() == 0
    assert grid.table.grad[:first_hashed_row].abs().max() > 0


def test_progressive_schedule() -> None:
    cfg = HashGridConfig(start_levels=8, start_step=2000, update_steps=500)
    assert [cfg.levels_at(s) for s in (0, 1999, 2000, 2499, 2500, 5000, 10_000)] == [8, 8, 8, 8, 9, 14, 16]
    assert HashGridConfig().levels_at(0) == 16
    with pytest.raises(ValueError, match="start_levels"):
        HashGridConfig(start_levels=0)


def test_reduced_precision_inputs_are_encoded_in_fp32(device: torch.device) -> None:
    grid = HashGrid(TINY, generator=torch.Generator().manual_seed(6)).to(device)
    x = torch.rand(32, 3, generator=torch.Generator().manual_seed(7)).to(device)
    ref = grid(x.to(torch.bfloat16).float())
    out = grid(x.to(torch.bfloat16))
    assert out.dtype == torch.float32 and torch.isfinite(out).all()
    torch.testing.assert_close(out, ref)


def _grad_case(active: int) -> tuple[HashGrid, torch.Tensor, torch.Tensor]:
    seed = int(np.random.default_rng().integers(1 << 30))
    g = torch.Generator().manual_seed(seed)
    cfg = HashGridConfig(n_levels=8, log2_table_size=9, base_resolution=4, per_level_scale=1.6)
    grid = HashGrid(cfg, generator=g)
    with torch.no_grad():
        grid.table.normal_(generator=g)
    grid.set_active_levels(active)
    return grid, torch.rand(500, 3, generator=g).requires_grad_(), torch.randn(500, cfg.output_dim, generator=g)


def test_the_backward_reusing_the_forward_s_corners_matches_finding_them_again() -> None:
    from morpheus_core.geometry.hashgrid import eager_encode_backward, eager_encode_forward

    grid, x, grad_out = _grad_case(8)
    out = grid(x)  # the autograd path: corners found once, kept for the backward
    out.backward(grad_out)
    tables, mask = grid.level_tables(), grid.level_mask
    want = eager_encode_forward(x.detach(), grid.table.detach(), tables, mask)
    want_gx, want_gt = eager_encode_backward(x.detach(), grid.table.detach(), tables, mask, grad_out, True, True)
    assert torch.equal(out.detach(), want) and torch.equal(x.grad, want_gx) and torch.equal(grid.table.grad, want_gt)


def test_levels_not_yet_switched_on_are_skipped_without_changing_the_encoding() -> None:
    """The CPU encode computes levels up to the last active one only; the masked levels still read as zeros."""
    from morpheus_core.geometry.hashgrid import eager_encode_backward, eager_encode_forward, encoded_levels

    grid, x, grad_out = _grad_case(5)
    assert encoded_levels(grid.level_mask) == 5
    out = grid(x)
    out.backward(grad_out)
    tables, mask = grid.level_tables(), grid.level_mask  # all 8 levels, the last three multiplied by 0
    want = eager_encode_forward(x.detach(), grid.table.detach(), tables, mask)
    want_gx, want_gt = eager_encode_backward(x.detach(), grid.table.detach(), tables, mask, grad_out, True, True)
    assert torch.equal(out.detach(), want) and torch.equal(grid.table.grad, want_gt)
    assert (out[:, 5 * 2:] == 0).all() and (grid.table.grad[tables.offsets[5]:] == 0).all()
    # The position gradient sums five levels instead of five and three zeros: the same up to the sum's order.
    torch.testing.assert_close(x.grad, want_gx, rtol=1e-6, atol=1e-6)


def test_the_table_gradient_is_autograd_s_bit_for_bit() -> None:
    """The hand-written backward sums each row's terms as autograd's gather backward does (on the CPU by one
    bincount per feature), so the table gradients are equal, not only close; many points share rows here."""
    from morpheus_core.geometry.hashgrid import eager_encode_backward, eager_encode_forward

    grid, x, grad_out = _grad_case(6)
    table = grid.table.detach().clone().requires_grad_()
    tables, mask = grid.level_tables(), grid.level_mask
    eager_encode_forward(x.detach(), table, tables, mask).backward(grad_out)
    _, hand = eager_encode_backward(x.detach(), table.detach(), tables, mask, grad_out, False, True)
    assert torch.equal(table.grad, hand) and table.grad.abs().sum() > 0
