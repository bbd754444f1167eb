"""Fused Triton kernels for the hash-grid encoding: forward and hand-written backward.

Same conventions and the same call signatures as ``eager_encode_forward`` / ``eager_encode_backward``
in ``hashgrid.py`` (the eager PyTorch code, which stays the CPU path and the reference): per level,
pos = x·float32(scale) + 0.5, cell = floor(pos), frac = pos − cell; dense levels index
x + y·res + z·res², hashed levels xor the coordinates times (1, 2654435761, 805459861) in uint32;
every index modulo the level's rows plus its row offset; trilinear weights ((w_z·w_y)·w_x, in the
eager code's order); the level mask multiplies features and gradients.

Where the eager code materialises (N, L, 8) index, weight and gathered-feature tensors, these
kernels keep one point's 8 corners in registers: the forward reads x once per level and writes the
(N, L·F) features; the backward scatters the table gradient with atomics and sums the analytic
input gradient Σ_corners (table[corner]·g)·∂w/∂pos·scale over the levels in registers. On the dense
(coarse) levels, where many points hit one row, consecutive points of a block that lie in the same
cell are summed first (a segmented scan over the block) and each run adds once: the NeRF stage's
samples come in such runs (neighbouring rays at one depth, a normal's six probes), and its hash-grid
backward took 2.5× less GPU time (``benchmarks/results/hashgrid_runs_summary_h200.md``).

Arithmetic: float32 inputs (fp16/bf16 tables are upcast inside, accumulation is fp32), with FMA
contraction switched off (``enable_fp_fusion=False``) so that x·scale + 0.5 rounds twice exactly as
the eager fp32 code does: the same cells, the same fractions, results equal to ~1e-6 relative
(only the summation order of the 8 corners, of the runs and of the atomics differs). Integer
indices are int32 (dense) and uint32 (hashed), as in tcnn: exact for inputs in [−1, 2] (``HashGrid``
clamps to [0, 1]).

The per-level device functions are in ``hashgrid_triton_levels``; the kernels and the host side here.
Triton reads ``TRITON_INTERPRET`` when ``@triton.jit`` runs, i.e. when this module is imported:
``hashgrid.py`` imports it lazily (only on CUDA, or under ``execution.hashgrid=triton``), and the CPU
tests set ``TRITON_INTERPRET=1`` before importing it.
"""

from __future__ import annotations

import weakref
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from morpheus_core.geometry.hashgrid_triton_levels import backward_level, forward_level, load_points
from morpheus_core.runtime.triton_support import device_guard, load_triton

triton, tl, _jit = load_triton()

if TYPE_CHECKING:
    from morpheus_core.geometry.hashgrid_layout import LevelTables

_BLOCK = 128  # points per program: 4 warps of 32 threads, one point per thread
_NUM_WARPS = 4
SUPPORTED_FEATURES = (1, 2, 4, 8)
SUPPORTED_TABLE_DTYPES = (torch.float32, torch.float16, torch.bfloat16)
RUN_REDUCTIONS = ("none", "dense", "all")
RUN_REDUCTION = "dense"
"""Levels whose table gradient sums runs of consecutive points in one cell before its atomics:
``dense``, ``all`` or ``none`` (an atomic per point and corner). ``benchmarks/hashgrid_runs.py``
times the three; the default is its measured choice (``all`` gains nothing over it: hashed rows are
nearly unique)."""


def supports(x: Tensor, table: Tensor) -> bool:
    """Whether these kernels take these inputs (fp32 points; fp32/fp16/bf16 tables of 1, 2, 4 or 8 features)."""
    return (x.dtype == torch.float32 and table.dtype in SUPPORTED_TABLE_DTYPES
            and table.dim() == 2 and table.shape[1] in SUPPORTED_FEATURES)


# ---------------------------------------------------------------------------------------------
# Kernels. Grid: a 2-D grid (blocks of points) × (levels), as tcnn's kernel_grid does, for the
# forward and for the table-only backward. One level per program multiplies the parallelism by L
# (2^16 points make 512 blocks, ×16 levels ≈ 8k programs to hide the gathers' latency), makes the
# level's constants and its dense-vs-hashed choice uniform per program (a compile-time branch, no
# divergence, no modulo computed twice), and keeps the programs that run together on one level's
# slice of the table, which then sits in L2. When the input gradient is wanted, the backward
# instead loops over the levels inside one program per block of points: grad_x sums over levels,
# and accumulating it in registers is deterministic and needs neither an (L, N, 3) buffer nor
# atomics on grad_x.
# ---------------------------------------------------------------------------------------------


@_jit
def _encode_kernel(x_ptr, base_ptr, table_ptr, out_ptr, scale_ptr, res_ptr, rows_ptr, offset_ptr, mask_ptr,
                   n_points, n_levels, n_dense, F: tl.constexpr, BLOCK: tl.constexpr, STACKED: tl.constexpr):
    level = tl.program_id(1)
    offs = (tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)).to(tl.int64)
    valid = offs < n_points
    x0, x1, x2, base = load_points(x_ptr, base_ptr, offs, valid, BLOCK, STACKED)
    if level < n_dense:  # dense levels are a prefix of the levels: uniform per program
        acc = forward_level(x0, x1, x2, base, valid, table_ptr, scale_ptr, res_ptr, rows_ptr, offset_ptr, mask_ptr,
                            level, F, BLOCK, False)
    else:
        acc = forward_level(x0, x1, x2, base, valid, table_ptr, scale_ptr, res_ptr, rows_ptr, offset_ptr, mask_ptr,
                            level, F, BLOCK, True)
    feats = tl.arange(0, F)
    ptrs = out_ptr + offs[:, None] * (n_levels * F) + level * F + feats[None, :]
    tl.store(ptrs, acc.to(out_ptr.dtype.element_ty), mask=valid[:, None])


@_jit
def _encode_backward_kernel(x_ptr, base_ptr, table_ptr, grad_out_ptr, grad_table_ptr, grad_x_ptr, scale_ptr,
                            res_ptr, rows_ptr, offset_ptr, mask_ptr, n_points, n_levels, n_dense,
                            F: tl.constexpr, BLOCK: tl.constexpr, WANT_X: tl.constexpr, WANT_TABLE: tl.constexpr,
                            STACKED: tl.constexpr, REDUCE_DENSE: tl.constexpr, REDUCE_HASHED: tl.constexpr):
    lane = tl.arange(0, BLOCK)
    offs = (tl.program_id(0) * BLOCK + lane).to(tl.int64)
    valid = offs < n_points
    x0, x1, x2, base = load_points(x_ptr, base_ptr, offs, valid, BLOCK, STACKED)
    first = lane == 0
    last = (lane == BLOCK - 1) | (offs + 1 >= n_points)
    if REDUCE_DENSE or REDUCE_HASHED:  # the neighbours' coordinates, to find runs of points in one cell
        before = load_points(x_ptr, base_ptr, offs - 1, valid & (lane > 0), BLOCK, STACKED)
        after = load_points(x_ptr, base_ptr, offs + 1, (offs + 1) < n_points, BLOCK, STACKED)
    else:
        before = (x0, x1, x2, base)
        after = before
    if WANT_X:  # grid (blocks, 1): every level in this program, grad_x summed in registers
        g0 = tl.zeros([BLOCK], dtype=tl.float32)
        g1 = tl.zeros([BLOCK], dtype=tl.float32)
        g2 = tl.zeros([BLOCK], dtype=tl.float32)
        for level in range(0, n_dense):
            d0, d1, d2 = backward_level(x0, x1, x2, base, offs, valid, before, after, first, last, table_ptr,
                                        grad_out_ptr, grad_table_ptr, scale_ptr, res_ptr, rows_ptr, offset_ptr,
                                        mask_ptr, level, n_levels, F, BLOCK, False, WANT_X, WANT_TABLE, REDUCE_DENSE)
            g0 += d0
            g1 += d1
            g2 += d2
        for level in range(n_dense, n_levels):
            d0, d1, d2 = backward_level(x0, x1, x2, base, offs, valid, before, after, first, last, table_ptr,
                                        grad_out_ptr, grad_table_ptr, scale_ptr, res_ptr, rows_ptr, offset_ptr,
                                        mask_ptr, level, n_levels, F, BLOCK, True, WANT_X, WANT_TABLE, REDUCE_HASHED)
            g0 += d0
            g1 += d1
            g2 += d2
        out_ty = grad_x_ptr.dtype.element_ty
        tl.store(grad_x_ptr + offs * 3, g0.to(out_ty), mask=valid)
        tl.store(grad_x_ptr + offs * 3 + 1, g1.to(out_ty), mask=valid)
        tl.store(grad_x_ptr + offs * 3 + 2, g2.to(out_ty), mask=valid)
    else:  # grid (blocks, levels): the table gradient alone, one level per program
        level = tl.program_id(1)
        if level < n_dense:
            backward_level(x0, x1, x2, base, offs, valid, before, after, first, last, table_ptr, grad_out_ptr,
                           grad_table_ptr, scale_ptr, res_ptr, rows_ptr, offset_ptr, mask_ptr, level, n_levels,
                           F, BLOCK, False, False, WANT_TABLE, REDUCE_DENSE)
        else:
            backward_level(x0, x1, x2, base, offs, valid, before, after, first, last, table_ptr, grad_out_ptr,
                           grad_table_ptr, scale_ptr, res_ptr, rows_ptr, offset_ptr, mask_ptr, level, n_levels,
                           F, BLOCK, True, False, WANT_TABLE, REDUCE_HASHED)


# ---------------------------------------------------------------------------------------------
# Host side.
# ---------------------------------------------------------------------------------------------

class _Constants:
    """The per-level constants as the kernels read them (device tensors, built once per LevelTables)."""

    def __init__(self, tables: LevelTables) -> None:
        self.scale = tables.scale.to(torch.float32).contiguous()  # = the eager fp32 path's scale.to(x.dtype)
        self.res = tables.strides[:, 1].to(torch.int32).contiguous()
        self.rows = tables.rows.to(torch.int32).contiguous()
        self.offsets = tables.offsets.to(torch.int64).contiguous()
        self.n_levels = int(tables.rows.shape[0])
        self.n_dense = int(tables.n_dense)


_constants: weakref.WeakKeyDictionary[Any, _Constants] = weakref.WeakKeyDictionary()


def _constants_for(tables: LevelTables) -> _Constants:
    consts = _constants.get(tables)
    if consts is None:
        consts = _constants[tables] = _Constants(tables)
    return consts


def _check(x: Tensor, table: Tensor, tables: LevelTables) -> _Constants:
    if triton is None:
        raise RuntimeError("the hash-grid Triton kernels need the triton package")
    if not supports(x, table):
        raise ValueError(f"hash-grid Triton kernels take float32 points and a float32/float16/bfloat16 table "
                         f"of {SUPPORTED_FEATURES} features; got x {x.dtype}, table {table.dtype} "
                         f"{tuple(table.shape)}")
    if x.dim() != 2 or x.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {tuple(x.shape)}")
    if x.device != table.device:
        raise ValueError(f"points on {x.device} but table on {table.device}")
    if x.device.type != "cuda" and type(_encode_kernel).__name__ != "InterpretedFunction":
        raise RuntimeError("hash-grid Triton kernels on a non-CUDA device need Triton's interpreter: set "
                           "TRITON_INTERPRET=1 before morpheus_core.geometry.hashgrid_triton is imported")
    consts = _constants_for(tables)
    if consts.scale.device != x.device:
        raise ValueError(f"level tables on {consts.scale.device} but points on {x.device}")
    return consts


def _launch_options() -> dict[str, Any]:
    # No FMA contraction: x·scale + 0.5 must round like the eager code's separate multiply and add.
    return {"num_warps": _NUM_WARPS, "enable_fp_fusion": False}


def _row_bases(x: Tensor, base: Tensor | None) -> Tensor:
    """The kernels' base pointer: the points' first table rows (several tables one after another;
    no pipeline path passes them since the stacked NeRF render went), or any int64 tensor when
    there is none (the STACKED flag then drops the load)."""
    if base is None:
        return x.new_zeros(1, dtype=torch.int64)
    if base.shape != (x.shape[0],) or base.device != x.device:
        raise ValueError(f"row bases must be ({x.shape[0]},) on {x.device}, got {tuple(base.shape)} on {base.device}")
    return base.to(torch.int64).contiguous()


def encode_forward(x: Tensor, table: Tensor, tables: LevelTables, level_mask: Tensor,
                   base: Tensor | None = None) -> Tensor:
    """(N, 3) points → (N, L·F) features in the table's dtype; as ``hashgrid.eager_encode_forward``."""
    consts = _check(x, table, tables)
    bases = _row_bases(x, base)
    x = x.contiguous()
    table = table.contiguous()
    mask = level_mask.to(device=x.device, dtype=torch.float32).contiguous()
    n, n_features = x.shape[0], table.shape[1]
    out = torch.empty((n, consts.n_levels * n_features), dtype=table.dtype, device=x.device)
    if n == 0:
        return out
    grid = (triton.cdiv(n, _BLOCK), consts.n_levels)
    with device_guard(x):
        _encode_kernel[grid](x, bases, table, out, consts.scale, consts.res, consts.rows, consts.offsets, mask,
                             n, consts.n_levels, consts.n_dense, F=n_features, BLOCK=_BLOCK,
                             STACKED=base is not None, **_launch_options())
    return out


def encode_backward(x: Tensor, table: Tensor, tables: LevelTables, level_mask: Tensor, grad_out: Tensor,
                    want_x: bool, want_table: bool, base: Tensor | None = None) -> tuple[Tensor | None, Tensor | None]:
    """(grad_x, grad_table), each None unless wanted; as ``hashgrid.eager_encode_backward``."""
    consts = _check(x, table, tables)
    bases = _row_bases(x, base)
    if RUN_REDUCTION not in RUN_REDUCTIONS:
        raise ValueError(f"hashgrid_triton.RUN_REDUCTION must be one of {RUN_REDUCTIONS}, got {RUN_REDUCTION!r}")
    if not (want_x or want_table):
        return None, None
    x = x.contiguous()
    table = table.contiguous()
    mask = level_mask.to(device=x.device, dtype=torch.float32).contiguous()
    n, n_features = x.shape[0], table.shape[1]
    if grad_out.shape != (n, consts.n_levels * n_features):
        raise ValueError(f"grad_out must be {(n, consts.n_levels * n_features)}, got {tuple(grad_out.shape)}")
    grad_out = grad_out.contiguous()
    # fp32 accumulation buffer for the atomics, whatever the table's dtype.
    grad_table = torch.zeros(table.shape, dtype=torch.float32, device=x.device) if want_table else None
    grad_x = torch.zeros((n, 3), dtype=x.dtype, device=x.device) if want_x else None
    if n > 0:
        # Runs are reduced only for the table gradient: an x-only backward skips the neighbours' loads.
        reduce_dense = want_table and RUN_REDUCTION in ("dense", "all")
        reduce_hashed = want_table and RUN_REDUCTION == "all"
        blocks = triton.cdiv(n, _BLOCK)
        grid = (blocks, 1) if want_x else (blocks, consts.n_levels)
        # Unwanted outputs: any valid pointer of the right dtype (the constexpr flags drop their code).
        gt = grad_table if grad_table is not None else x
        gx = grad_x if grad_x is not None else x
        with device_guard(x):
            _encode_backward_kernel[grid](x, bases, table, grad_out, gt, gx, consts.scale, consts.res, consts.rows,
                                          consts.offsets, mask, n, consts.n_levels, consts.n_dense, F=n_features,
                                          BLOCK=_BLOCK, WANT_X=bool(want_x), WANT_TABLE=bool(want_table),
                                          STACKED=base is not None, REDUCE_DENSE=reduce_dense,
                                          REDUCE_HASHED=reduce_hashed, **_launch_options())
    if grad_table is not None and grad_table.dtype != table.dtype:
        grad_table = grad_table.to(table.dtype)
    return grad_x, grad_table
