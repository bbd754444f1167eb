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

from collections.abc import Callable, Sequence
from types import ModuleType

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from morpheus_core.geometry.hashgrid_layout import HashGridConfig, LevelTables
from morpheus_core.runtime.devices import compile_enabled, compiled_for
from morpheus_core.runtime.execution import current_execution
from morpheus_core.runtime.triton_support import choose

_INIT_SCALE = 1e-4  # tcnn's uniform(−1e-4, 1e-4) table initialisation


# Per-axis values are kept as planes: ``planes[d][c]`` is axis d's value (d = x, y, z) at the lower (c = 0) or
# upper (c = 1) corner, an (N, L) tensor or a number. Laid out with the axes first, every elementwise pass runs
# over long contiguous rows; with the 3 × 2 corner dims last they ran 3× slower on the CPU (inner loops of
# length 2), for the same numbers.
Planes = Sequence[Sequence[Tensor | float]]


def _corner_product(planes: Planes, op: Callable[[Tensor, Tensor | float], Tensor]) -> Tensor:
    """The 8 corners' values (N, L, 8) from per-axis planes. Corner c = cx + 2·cy + 4·cz (bit d selects the upper
    corner on axis d); ``op`` is how the three axes meet: ``torch.mul`` for trilinear weights, ``torch.add`` for
    dense indices, ``torch.bitwise_xor`` for hashes, always as (z ∘ y) ∘ x."""
    zy = [op(planes[2][cz], planes[1][cy]) for cz in (0, 1) for cy in (0, 1)]  # index 2·cz + cy
    return torch.stack([op(zy[c >> 1], planes[0][c & 1]) for c in range(8)], -1)


def _with_upper(lower: Tensor, step: Tensor) -> Planes:
    """Planes of the lower corners' values (3, N, L) and the upper ones', ``step`` (3, 1, L) more per axis."""
    return [(lower[d], lower[d] + step[d]) for d in range(3)]


def _positions(x: Tensor, tables: LevelTables) -> tuple[Tensor, Tensor]:
    """Integer cell (3, N, L) and fraction (3, N, L) of every point on every level, per axis.

    Positions are formed in the input's dtype: float32 rounding of x·scale matches tcnn's own
    float arithmetic, float64 keeps gradcheck exact.
    """
    pos = x.t().unsqueeze(-1) * tables.scale.to(x.dtype) + 0.5
    base = torch.floor(pos)
    return base.to(torch.int64), pos - base


def _row_indices(cell: Tensor, tables: LevelTables, base: Tensor | None = None) -> Tensor:
    """(N, L, 8) rows of the flat table holding each corner's features; ``base`` (N,): each point's
    first row in a table of several tables one after another (the reference for the kernels' row
    bases, ``hashgrid_triton.encode_forward``)."""
    k = tables.n_dense
    parts = []
    if k > 0:  # dense: x + res·y + res²·z, wrapped at the level's size (x = 1 lies one past the grid)
        strides = tables.strides[:k].t().unsqueeze(1)  # (3, 1, k)
        lower = cell[:, :, :k] * strides  # (3, N, k)
        dense = _corner_product(_with_upper(lower, strides), torch.add)
        parts.append(torch.remainder(dense, tables.rows[:k].reshape(1, -1, 1)))
    if k < tables.n_levels:
        # tcnn hashes in uint32: the low 32 bits of the int64 products, xor-ed. Hashed levels hold
        # 2^log2_table_size ≤ 2^30 rows, so the modulo is a mask of low bits (cheaper on the CPU than a
        # remainder) and the same mask drops the high bits uint32 would have lost.
        primes = tables.primes.reshape(3, 1, 1)
        lower = cell[:, :, k:] * primes
        hashed = _corner_product(_with_upper(lower, primes), torch.bitwise_xor)
        parts.append(hashed & (tables.rows[k:].reshape(1, -1, 1) - 1))
    idx = parts[0] if len(parts) == 1 else torch.cat(parts, 1)
    rows = idx + tables.offsets.reshape(1, -1, 1)
    return rows if base is None else rows + base.reshape(-1, 1, 1)


def _rows_of(table: Tensor, idx: Tensor) -> Tensor:
    """``table[idx]`` (..., F): ``index_select`` on the flat indices gathers the same rows in half the CPU time."""
    return table.index_select(0, idx.reshape(-1)).view(*idx.shape, table.shape[1])


Corners = tuple[Tensor, Tensor, Tensor]
"""What ``corners`` finds: table rows (N, L, 8), weight planes (3, 2, N, L), trilinear weights (N, L, 8)."""


def corners(x: Tensor, tables: LevelTables, base: Tensor | None = None) -> Corners:
    """Every point's 8 corners on every level: their table rows (N, L, 8), the weight planes of the lower and
    upper corner per axis (3, 2, N, L): 1 − f and f, and the corners' trilinear weights (N, L, 8), in the points'
    dtype. The eager encode computes them once for its forward and backward."""
    cell, frac = _positions(x, tables)
    axis_w = torch.stack((1 - frac, frac), 1)
    return _row_indices(cell, tables, base), axis_w, _corner_product(axis_w, torch.mul)


def eager_encode_forward(x: Tensor, table: Tensor, tables: LevelTables, level_mask: Tensor,
                         base: Tensor | None = None, found: Corners | None = None) -> Tensor:
    """(N, 3) points → (N, L·F) features in the table's dtype, by tensor ops: the Triton kernels' reference.
    ``found``: ``corners(x, tables, base)`` when the caller has them."""
    idx, _, weights = found if found is not None else corners(x, tables, base)
    weights = weights.to(table.dtype)
    corner_rows = _rows_of(table, idx)  # (N, L, 8, F)
    # The weights expanded to the rows' shape first: the same products, without a broadcast over F.
    out = (corner_rows * weights.unsqueeze(-1).expand_as(corner_rows).contiguous()).sum(-2)
    out = out * level_mask.reshape(1, -1, 1).to(table.dtype)
    return out.flatten(1)  # (N, L·F), also for N = 0


def _table_gradient(table: Tensor, idx: Tensor, g: Tensor, weights: Tensor) -> Tensor:
    """Σ over points and corners of weight × output gradient, into each corner's row: (rows, F).

    On the CPU one ``bincount`` per feature: it adds each row's terms in the same order as ``index_add_`` (the
    same sums, bit for bit) at a quarter of its time, which loops over rows of F = 2 values. Elsewhere (and for
    other dtypes) ``index_add_``: CUDA's bincount adds in no fixed order and its output size depends on the data,
    which ``torch.compile`` cannot trace.
    """
    if table.device.type == "cpu" and table.dtype == g.dtype and table.dtype in (torch.float32, torch.float64):
        flat = idx.reshape(-1)
        return torch.stack([torch.bincount(flat, weights=(g[..., f].unsqueeze(-1) * weights).reshape(-1),
                                           minlength=table.shape[0]) for f in range(table.shape[1])], 1)
    contrib = (g.unsqueeze(-2) * weights.unsqueeze(-1)).reshape(-1, table.shape[1])
    return torch.zeros_like(table).index_add_(0, idx.reshape(-1), contrib.to(table.dtype))


def eager_encode_backward(x: Tensor, table: Tensor, tables: LevelTables, level_mask: Tensor, grad_out: Tensor,
                          want_x: bool, want_table: bool, base: Tensor | None = None,
                          found: Corners | None = None) -> tuple[Tensor | None, Tensor | None]:
    """(grad_x, grad_table) of ``eager_encode_forward``, each None unless wanted (the hand-written backward).
    ``found``: the forward's ``corners``, else they are computed again."""
    idx, axis_w, weights = found if found is not None else corners(x, tables, base)
    mask = level_mask.reshape(1, -1, 1).to(grad_out.dtype)
    g = grad_out.reshape(x.shape[0], level_mask.shape[0], table.shape[1]) * mask
    grad_table = None
    if want_table:
        grad_table = _table_gradient(table, idx, g, weights.to(g.dtype))
    grad_x = None
    if want_x:
        corner_dot = (_rows_of(table, idx).to(x.dtype) * g.unsqueeze(-2).to(x.dtype)).sum(-1)  # (N, L, 8)
        grads = []
        for d in range(3):
            # ∂w/∂f_d: axis d contributes its slope (∓1), the other axes their weights.
            per_axis = [(-1.0, 1.0) if a == d else axis_w[a] for a in range(3)]
            grads.append((corner_dot * _corner_product(per_axis, torch.mul)).sum(-1))  # (N, L)
        grad_pos = torch.stack(grads, -1)
        grad_x = (grad_pos * tables.scale.to(x.dtype).reshape(1, -1, 1)).sum(-2)
    return grad_x, grad_table


def encoded_levels(level_mask: Tensor) -> int:
    """How many levels, from the first, the eager CPU encode computes: up to the last active one. Levels
    past it (progressive masking switches the fine ones on late) output zeros and get no gradient, so
    skipping them changes no number; a fifth of the draft NeRF stage's encode. Elsewhere all levels:
    reading the mask would wait for the device."""
    if level_mask.device.type != "cpu":
        return level_mask.shape[0]
    active = torch.nonzero(level_mask)
    return int(active[-1]) + 1 if active.numel() else level_mask.shape[0]


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
        n = encoded_levels(level_mask)
        ctx.encoded = part = tables.first(n)
        ctx.found = corners(x, part)
        out = eager_encode_forward(x, table, part, level_mask[:n], found=ctx.found)
        return out if n == level_mask.shape[0] else F.pad(out, (0, (level_mask.shape[0] - n) * table.shape[1]))

    @staticmethod
    def backward(ctx, grad_out: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        x, level_mask, table = ctx.saved_tensors
        want_x, want_table = bool(ctx.needs_input_grad[0]), bool(ctx.needs_input_grad[1])
        if ctx.found is not None:  # eager: the forward's corners, on the levels it encoded
            n = ctx.encoded.n_levels
            grad_x, grad_table = eager_encode_backward(
                x, table, ctx.encoded, level_mask[:n], grad_out[:, :n * table.shape[1]].contiguous(),
                want_x, want_table, found=ctx.found)
            return grad_x, grad_table, None, None
        args = (x, table, ctx.tables, level_mask, grad_out.contiguous(), want_x, want_table)
        if ctx.kernels is not None:
            grad_x, grad_table = ctx.kernels.encode_backward(*args)
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
