"""Device functions of the hash-grid Triton kernels (``hashgrid_triton``): one level's cells and
fractions, a corner's table row and trilinear weights, the forward's gather of one level, and the
backward's scatter of one level, with the run reduction of the dense levels.

The backward's run reduction: consecutive points of a block that lie in one cell of a level (and
belong to one object) form a run; a segmented scan sums the run's contributions for all 8 corners
at once and the run's last point adds them with one atomic, where each point would otherwise add
its own. Imported only by ``hashgrid_triton``, so ``TRITON_INTERPRET`` is read when that is.
"""

from __future__ import annotations

from morpheus_core.runtime.triton_support import load_triton

triton, tl, _jit = load_triton()


@_jit
def _level_frame(x0, x1, x2, scale):
    """Integer cell and fraction per axis: pos = x·scale + 0.5 (two roundings, no FMA)."""
    p0 = x0 * scale + 0.5
    p1 = x1 * scale + 0.5
    p2 = x2 * scale + 0.5
    b0 = tl.floor(p0)
    b1 = tl.floor(p1)
    b2 = tl.floor(p2)
    return b0.to(tl.int32), b1.to(tl.int32), b2.to(tl.int32), p0 - b0, p1 - b1, p2 - b2


@_jit
def _corner_row(c0, c1, c2, res, rows, offset, CORNER, HASHED: tl.constexpr):
    """Flat table row of corner CORNER = bx + 2·by + 4·bz of the cells (c0, c1, c2): one corner (a
    constant), or a tensor of corners that broadcasts against the cells."""
    cx = c0 + (CORNER & 1)
    cy = c1 + ((CORNER >> 1) & 1)
    cz = c2 + ((CORNER >> 2) & 1)
    if HASHED:
        # uint32 products wrap exactly like tcnn's (and like the eager int64 product & 0xFFFFFFFF).
        h = cx.to(tl.uint32) ^ (cy.to(tl.uint32) * 2654435761) ^ (cz.to(tl.uint32) * 805459861)
        row = (h % rows.to(tl.uint32)).to(tl.int64)
    else:
        d = cx + cy * res + cz * (res * res)
        d = d % rows
        row = tl.where(d < 0, d + rows, d).to(tl.int64)  # floor modulo, as torch.remainder
    return row + offset


@_jit
def _axis_weights(f0, f1, f2, CORNER: tl.constexpr):
    """Per-axis trilinear weights of corner CORNER: the upper corner's f, the lower's 1 − f."""
    if CORNER & 1:
        wx = f0
    else:
        wx = 1 - f0
    if (CORNER >> 1) & 1:
        wy = f1
    else:
        wy = 1 - f1
    if (CORNER >> 2) & 1:
        wz = f2
    else:
        wz = 1 - f2
    return wx, wy, wz


@_jit
def _level_setup(x0, x1, x2, valid, scale_ptr, res_ptr, rows_ptr, offset_ptr, mask_ptr, level, BLOCK: tl.constexpr):
    """One level's constants, the points' cells and fractions in it, and which points it touches: a
    masked level (m = 0) reads and scatters nothing. (m is broadcast first: the interpreter cannot
    `&` a scalar bool with a block.)"""
    scale = tl.load(scale_ptr + level)
    res = tl.load(res_ptr + level)
    rows = tl.load(rows_ptr + level)
    offset = tl.load(offset_ptr + level)
    m = tl.load(mask_ptr + level)
    c0, c1, c2, f0, f1, f2 = _level_frame(x0, x1, x2, scale)
    active = valid & ((tl.zeros([BLOCK], dtype=tl.float32) + m) != 0.0)
    return scale, res, rows, offset, m, c0, c1, c2, f0, f1, f2, active


# One level's trilinear gather: the block's (BLOCK, F) features, times the level's mask.
@_jit
def forward_level(x0, x1, x2, base, valid, table_ptr, scale_ptr, res_ptr, rows_ptr, offset_ptr, mask_ptr, level,
                  F: tl.constexpr, BLOCK: tl.constexpr, HASHED: tl.constexpr):
    _scale, res, rows, offset, m, c0, c1, c2, f0, f1, f2, active = _level_setup(
        x0, x1, x2, valid, scale_ptr, res_ptr, rows_ptr, offset_ptr, mask_ptr, level, BLOCK)
    feats = tl.arange(0, F)
    acc = tl.zeros([BLOCK, F], dtype=tl.float32)
    for corner in tl.static_range(8):
        row = _corner_row(c0, c1, c2, res, rows, offset, corner, HASHED) + base
        wx, wy, wz = _axis_weights(f0, f1, f2, corner)
        w = (wz * wy) * wx
        vals = tl.load(table_ptr + row[:, None] * F + feats[None, :], mask=active[:, None], other=0.0)
        acc += vals.to(tl.float32) * w[:, None]
    return acc * m


@_jit
def load_points(x_ptr, base_ptr, offs, valid, BLOCK: tl.constexpr, STACKED: tl.constexpr):
    """A block's coordinates, and the first table row of each point's object (0 unless STACKED)."""
    x0 = tl.load(x_ptr + offs * 3, mask=valid, other=0.0)
    x1 = tl.load(x_ptr + offs * 3 + 1, mask=valid, other=0.0)
    x2 = tl.load(x_ptr + offs * 3 + 2, mask=valid, other=0.0)
    if STACKED:
        base = tl.load(base_ptr + offs, mask=valid, other=0)
    else:
        base = tl.zeros([BLOCK], dtype=tl.int64)
    return x0, x1, x2, base


@_jit
def _segment_sum(flag_a, sum_a, flag_b, sum_b):
    """Segmented inclusive sum: a set flag starts a new run. Associative, so the scan may combine
    in any tree; at a run's last element the sum is the whole run's."""
    return flag_a | flag_b, tl.where(flag_b != 0, sum_b, sum_a + sum_b)


@_jit
def _same_cell(c0, c1, c2, base, y0, y1, y2, y_base, scale):
    """Whether the points y lie in the same cell (and object) of this level as the cells (c0, c1, c2)."""
    n0, n1, n2, _f0, _f1, _f2 = _level_frame(y0, y1, y2, scale)
    return (c0 == n0) & (c1 == n1) & (c2 == n2) & (base == y_base)


@_jit
def _scatter_runs(c0, c1, c2, f0, f1, f2, base, g, head, tail, active, grad_table_ptr, res, rows, offset,
                  F: tl.constexpr, BLOCK: tl.constexpr, HASHED: tl.constexpr):
    """A level's table gradient with one atomic per run of consecutive points in one cell (``head``:
    a run starts here, ``tail``: it ends here): all 8 corners' contributions at once, (BLOCK, 8, F),
    summed along the block by a segmented scan, and added from each run's last point."""
    corners = tl.arange(0, 8)[None, :]
    wx = tl.where((corners & 1) != 0, f0[:, None], 1 - f0[:, None])
    wy = tl.where(((corners >> 1) & 1) != 0, f1[:, None], 1 - f1[:, None])
    wz = tl.where(((corners >> 2) & 1) != 0, f2[:, None], 1 - f2[:, None])
    w = (wz * wy) * wx  # (BLOCK, 8), the per-corner code's order
    row = _corner_row(c0[:, None], c1[:, None], c2[:, None], res, rows, offset, corners, HASHED) + base[:, None]
    feats = tl.arange(0, F)
    flags = tl.broadcast_to(head.to(tl.int32)[:, None, None], (BLOCK, 8, F))
    _flags, sums = tl.associative_scan((flags, g[:, None, :] * w[:, :, None]), 0, _segment_sum)
    ptrs = grad_table_ptr + row[:, :, None] * F + feats[None, None, :]
    tl.atomic_add(ptrs, sums, mask=(active & tail)[:, None, None], sem="relaxed")


@_jit
def backward_level(x0, x1, x2, base, offs, valid, before, after, first, last, table_ptr, grad_out_ptr, grad_table_ptr,
                   scale_ptr, res_ptr, rows_ptr, offset_ptr, mask_ptr, level, n_levels, F: tl.constexpr,
                   BLOCK: tl.constexpr, HASHED: tl.constexpr, WANT_X: tl.constexpr, WANT_TABLE: tl.constexpr,
                   REDUCE: tl.constexpr):
    """One level's table-gradient scatter; returns its (∂L/∂x, ∂L/∂y, ∂L/∂z) contribution. ``before`` and
    ``after``: the neighbouring points' (x, y, z, row base), read when REDUCE sums runs of points in one
    cell before the atomics (``first``/``last``: lanes where a run must start/end)."""
    scale, res, rows, offset, m, c0, c1, c2, f0, f1, f2, active = _level_setup(
        x0, x1, x2, valid, scale_ptr, res_ptr, rows_ptr, offset_ptr, mask_ptr, level, BLOCK)
    feats = tl.arange(0, F)
    g_ptrs = grad_out_ptr + offs[:, None] * (n_levels * F) + level * F + feats[None, :]
    g = tl.load(g_ptrs, mask=active[:, None], other=0.0).to(tl.float32) * m
    if WANT_TABLE:
        if REDUCE:
            # Samples along a ray, neighbouring rays and a normal's six probes come in runs that share
            # a cell of the coarse levels; one atomic per run instead of per point takes the contention
            # off the rows that many points hit (level 0: 16^3 rows for 2^18 points).
            head = first | (_same_cell(c0, c1, c2, base, before[0], before[1], before[2], before[3], scale) == 0)
            tail = last | (_same_cell(c0, c1, c2, base, after[0], after[1], after[2], after[3], scale) == 0)
            _scatter_runs(c0, c1, c2, f0, f1, f2, base, g, head, tail, active, grad_table_ptr, res, rows, offset,
                          F, BLOCK, HASHED)
    d0 = tl.zeros([BLOCK], dtype=tl.float32)
    d1 = tl.zeros([BLOCK], dtype=tl.float32)
    d2 = tl.zeros([BLOCK], dtype=tl.float32)
    for corner in tl.static_range(8):
        row = _corner_row(c0, c1, c2, res, rows, offset, corner, HASHED) + base
        wx, wy, wz = _axis_weights(f0, f1, f2, corner)
        row_ptrs = row[:, None] * F + feats[None, :]
        if WANT_TABLE:
            if not REDUCE:  # one atomic per point and corner: rows of the hashed levels are nearly unique
                w = (wz * wy) * wx
                tl.atomic_add(grad_table_ptr + row_ptrs, g * w[:, None], mask=active[:, None], sem="relaxed")
        if WANT_X:
            vals = tl.load(table_ptr + row_ptrs, mask=active[:, None], other=0.0).to(tl.float32)
            dot = tl.sum(vals * g, axis=1)
            # ∂w/∂f_d: axis d's slope (∓1) times the other two axes' weights.
            if corner & 1:
                d0 += dot * (wz * wy)
            else:
                d0 -= dot * (wz * wy)
            if (corner >> 1) & 1:
                d1 += dot * (wz * wx)
            else:
                d1 -= dot * (wz * wx)
            if (corner >> 2) & 1:
                d2 += dot * (wy * wx)
            else:
                d2 -= dot * (wy * wx)
    return d0 * scale, d1 * scale, d2 * scale
