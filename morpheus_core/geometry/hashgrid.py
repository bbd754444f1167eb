"""Multi-resolution hash-grid encoding in pure PyTorch, with tiny-cuda-nn's conventions.

Per level l: scale = b^l·N_min − 1, res = ceil(scale) + 1, pos = x·scale + 0.5; the level is a
dense grid when res³ fits the table (its size rounded up to a multiple of 8, as tcnn does),
otherwise a spatial hash with primes (1, 2654435761, 805459861). Indices are taken modulo the
level's size, so x = 1 (whose upper corner lies one past the grid) wraps exactly like tcnn.

The backward is written by hand: the table gradient is a single ``index_add_`` (autograd's
gather backward would build a dense (N·L·8, F) intermediate and scatter it), and the input
gradient is the analytic derivative of the trilinear weights — the texture field needs it to
pass colour gradients on to mesh vertices.

Kernels: on CUDA the encode runs as fused Triton kernels (``hashgrid_triton``: one gather pass per
level in registers, table gradient by atomics, one per run of points in a cell on the dense levels,
the same arithmetic as the code here), when Triton imports; otherwise (and for float64 inputs) the
pure tensor functions below, compiled on CUDA (``compiled_for``). The CPU always runs the eager code
below, unchanged. ``execution.hashgrid`` (``morpheus_core.runtime.execution``, alias ``MORPHEUS_HASHGRID``)
picks: ``auto`` (the default: Triton on CUDA where available), ``triton`` (insist: an error where
Triton cannot run, e.g. a CPU without ``TRITON_INTERPRET=1``), ``eager`` (the tensor code
everywhere: debugging, the benchmarks' "before"). It is a process-wide execution setting, not a
stage config field, because it does not change results beyond float rounding and must not change
the fingerprints of existing stores.
"""

from __future__ import annotations

from types import ModuleType

import torch
from torch import Tensor, nn

from morpheus_core.geometry.hashgrid_layout import HashGridConfig, LevelTables
from morpheus_core.runtime.devices import compile_enabled, compiled_for
from morpheus_core.runtime.execution import current_execution
from morpheus_core.runtime.triton_support import choose

_INIT_SCALE = 1e-4  # tcnn's uniform(−1e-4, 1e-4) table initialisation


def _corner_product(per_axis: Tensor, combine: str) -> Tensor:
    """(..., 3, 2) per-axis values of the lower/upper corner → (..., 8) values of the 8 corners.

    Corner c = cx + 2·cy + 4·cz (bit d selects the upper corner on axis d); ``combine`` is how the
    three axes meet: "mul" for trilinear weights, "add" for dense indices, "xor" for hashes, always as
    (z ∘ y) ∘ x. The six per-axis values are first laid out as contiguous planes: broadcasting over the
    trailing 2 × 2 × 2 corner dims ran 3× slower on the CPU (inner loops of length 2), for the same numbers.
    """
    op = {"mul": torch.mul, "add": torch.add, "xor": torch.bitwise_xor}[combine]
    planes = per_axis.movedim((-2, -1), (0, 1)).contiguous()  # (3, 2, ...)
    zy = [op(planes[2, cz], planes[1, cy]) for cz in (0, 1) for cy in (0, 1)]  # index 2·cz + cy
    return torch.stack([op(zy[c >> 1], planes[0, c & 1]) for c in range(8)], -1)


def _positions(x: Tensor, tables: LevelTables) -> tuple[Tensor, Tensor]:
    """Integer cell (N, L, 3) and fraction (N, L, 3) of every point on every level.

    Positions are formed in the input's dtype: float32 rounding of x·scale matches tcnn's own
    float arithmetic, float64 keeps gradcheck exact.
    """
    pos = x.unsqueeze(-2) * tables.scale.to(x.dtype).unsqueeze(-1) + 0.5
    base = torch.floor(pos)
    return base.to(torch.int64), pos - base


def _row_indices(cell: Tensor, tables: LevelTables, base: Tensor | None = None) -> Tensor:
    """(N, L, 8) rows of the flat table holding each corner's features; ``base`` (N,): each point's
    first row in a table of several tables one after another (the reference for the kernels' row
    bases, ``hashgrid_triton.encode_forward``)."""
    coords = cell.unsqueeze(-1) + tables.steps  # (N, L, 3, 2)
    k = tables.n_dense
    dense = _corner_product(coords[:, :k] * tables.strides[:k].unsqueeze(-1), "add")
    # tcnn multiplies in uint32; the low 32 bits of the int64 product are the same number.
    hashed = _corner_product((coords[:, k:] * tables.primes.unsqueeze(-1)) & 0xFFFFFFFF, "xor")
    # Hashed levels hold 2^log2_table_size rows and their hashes are ≥ 0, so the modulo is a mask (cheaper on
    # the CPU than a remainder, the same numbers).
    idx = torch.cat((torch.remainder(dense, tables.rows[:k].reshape(1, -1, 1)),
                     hashed & (tables.rows[k:].reshape(1, -1, 1) - 1)), 1)
    rows = idx + tables.offsets.reshape(1, -1, 1)
    return rows if base is None else rows + base.reshape(-1, 1, 1)


def _axis_weights(frac: Tensor) -> Tensor:
    """(N, L, 3, 2): the lower corner's (1 − f) and the upper corner's f per axis."""
    return torch.stack((1 - frac, frac), -1)


def _rows_of(table: Tensor, idx: Tensor) -> Tensor:
    """``table[idx]`` (..., F): ``index_select`` on the flat indices gathers the same rows in half the CPU time."""
    return table.index_select(0, idx.reshape(-1)).view(*idx.shape, table.shape[1])


def corners(x: Tensor, tables: LevelTables, base: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Every point's 8 corners on every level: their table rows (N, L, 8) and the per-axis weights of the lower
    and upper corner (N, L, 3, 2). The eager encode computes them once for its forward and backward."""
    cell, frac = _positions(x, tables)
    return _row_indices(cell, tables, base), _axis_weights(frac)


def eager_encode_forward(x: Tensor, table: Tensor, tables: LevelTables, level_mask: Tensor,
                         base: Tensor | None = None, found: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """(N, 3) points → (N, L·F) features in the table's dtype, by tensor ops: the Triton kernels' reference.
    ``found``: ``corners(x, tables, base)`` when the caller has them."""
    idx, axis_w = found if found is not None else corners(x, tables, base)
    weights = _corner_product(axis_w, "mul").to(table.dtype)
    corner_rows = _rows_of(table, idx)  # (N, L, 8, F)
    # The weights expanded to the rows' shape first: the same products, without a broadcast over F.
    out = (corner_rows * weights.unsqueeze(-1).expand_as(corner_rows).contiguous()).sum(-2)
    out = out * level_mask.reshape(1, -1, 1).to(table.dtype)
    return out.flatten(1)  # (N, L·F), also for N = 0


def eager_encode_backward(x: Tensor, table: Tensor, tables: LevelTables, level_mask: Tensor, grad_out: Tensor,
                          want_x: bool, want_table: bool, base: Tensor | None = None,
                          found: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor | None, Tensor | None]:
    """(grad_x, grad_table) of ``eager_encode_forward``, each None unless wanted (the hand-written backward).
    ``found``: the forward's ``corners``, else they are computed again."""
    idx, axis_w = found if found is not None else corners(x, tables, base)
    mask = level_mask.reshape(1, -1, 1).to(grad_out.dtype)
    g = grad_out.reshape(x.shape[0], level_mask.shape[0], table.shape[1]) * mask
    grad_table = None
    if want_table:
        weights = _corner_product(axis_w, "mul").to(g.dtype)
        contrib = (g.unsqueeze(-2) * weights.unsqueeze(-1)).reshape(-1, table.shape[1])
        grad_table = torch.zeros_like(table).index_add_(0, idx.reshape(-1), contrib.to(table.dtype))
    grad_x = None
    if want_x:
        corner_dot = (_rows_of(table, idx).to(x.dtype) * g.unsqueeze(-2).to(x.dtype)).sum(-1)  # (N, L, 8)
        slope = torch.tensor([-1.0, 1.0], dtype=x.dtype, device=x.device).expand_as(axis_w)
        grads = []
        for d in range(3):
            # ∂w/∂f_d: axis d contributes its slope (∓1), the other axes their weights.
            per_axis = torch.where(torch.arange(3, device=x.device).reshape(1, 1, 3, 1) == d, slope, axis_w)
            grads.append((corner_dot * _corner_product(per_axis, "mul")).sum(-1))  # (N, L)
        grad_pos = torch.stack(grads, -1)
        grad_x = (grad_pos * tables.scale.to(x.dtype).reshape(1, -1, 1)).sum(-2)
    return grad_x, grad_table


def triton_kernels(x: Tensor, table: Tensor) -> ModuleType | None:
    """The Triton kernel module when this encode should use it (``execution.hashgrid``,
    ``triton_support.choose``), else None."""

    def load() -> ModuleType:
        from morpheus_core.geometry import hashgrid_triton

        return hashgrid_triton

    choice = current_execution().hashgrid
    return choose(choice, "execution.hashgrid", x.device, lambda: load().supports(x, table), load, "hash-grid")


class _HashEncode(torch.autograd.Function):
    """Fused Triton kernels on CUDA, else pure tensor functions, compiled on CUDA (``compiled_for``)."""

    @staticmethod
    def forward(ctx, x: Tensor, table: Tensor, tables: LevelTables, level_mask: Tensor) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(x, level_mask, table)
        ctx.tables = tables
        ctx.kernels = kernels = triton_kernels(x, table)  # the backward uses the forward's choice
        ctx.found = None
        if kernels is not None:
            return kernels.encode_forward(x, table, tables, level_mask)
        if compile_enabled(x.device):  # one compiled graph each way; the backward finds the corners again
            return compiled_for(eager_encode_forward, x.device)(x, table, tables, level_mask)
        # Eager (the CPU): finding the corners costs as much as the gather, so the backward reuses them.
        ctx.found = corners(x, tables)
        return eager_encode_forward(x, table, tables, level_mask, found=ctx.found)

    @staticmethod
    def backward(ctx, grad_out: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        x, level_mask, table = ctx.saved_tensors
        want_x, want_table = bool(ctx.needs_input_grad[0]), bool(ctx.needs_input_grad[1])
        args = (x, table, ctx.tables, level_mask, grad_out.contiguous(), want_x, want_table)
        if ctx.kernels is not None:
            grad_x, grad_table = ctx.kernels.encode_backward(*args)
        elif ctx.found is not None:  # eager: the forward's corners
            grad_x, grad_table = eager_encode_backward(*args, found=ctx.found)
        else:  # compiled: one graph each way
            grad_x, grad_table = compiled_for(eager_encode_backward, x.device)(*args)
        return grad_x, grad_table, None, None


class HashGrid(nn.Module):
    """Encodes points in [0, 1]^3 (clamped) into ``config.output_dim`` features."""

    def __init__(self, config: HashGridConfig, generator: torch.Generator | None = None) -> None:
        super().__init__()
        self.config = config
        rows = sum(n for _, _, n, _ in config.level_layout())
        init = (torch.rand(rows, config.n_features_per_level, generator=generator) * 2 - 1) * _INIT_SCALE
        self.table = nn.Parameter(init)
        self.register_buffer("level_mask", torch.ones(config.n_levels), persistent=True)
        self._tables: LevelTables | None = None
        self.set_active_levels(config.levels_at(0))

    @property
    def output_dim(self) -> int:
        return self.config.output_dim

    @property
    def active_levels(self) -> int:
        return int(self.level_mask.sum().item())

    def set_active_levels(self, n: int) -> None:
        """Zero the features of levels ≥ n (coarse-to-fine training); their table gets no gradient."""
        if not 1 <= n <= self.config.n_levels:
            raise ValueError(f"active levels must be in [1, {self.config.n_levels}], got {n}")
        with torch.no_grad():  # built on the mask's device: a host tensor's copy would sync every step
            levels = torch.arange(self.config.n_levels, device=self.level_mask.device)
            self.level_mask.copy_((levels < n).to(self.level_mask.dtype))

    def update_step(self, step: int) -> None:
        self.set_active_levels(self.config.levels_at(step))

    def level_tables(self) -> LevelTables:
        """This grid's per-level constants on the table's device (cached; the encoders' ``tables`` argument)."""
        device = self.table.device
        if self._tables is None or self._tables.scale.device != device:
            self._tables = LevelTables(self.config, device)
        return self._tables

    def forward(self, x: Tensor) -> Tensor:
        out = _HashEncode.apply(_flat_points(x), self.table, self.level_tables(), self.level_mask)
        return out.reshape(*x.shape[:-1], self.output_dim)


def _flat_points(x: Tensor) -> Tensor:
    if x.shape[-1] != 3:
        raise ValueError(f"hash grid inputs must be (..., 3), got {tuple(x.shape)}")
    flat = x.reshape(-1, 3)
    # Reduced-precision inputs would quantise positions to a few grid cells: encode in fp32 at least.
    if flat.dtype not in (torch.float32, torch.float64):
        flat = flat.float()
    return flat.clamp(0.0, 1.0)
