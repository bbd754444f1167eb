"""Fused Triton kernels for the NeRF field's two heads: the density and albedo MLPs of two hidden
ReLU layers each, read from the same hash-grid features, forward and hand-written backward.

The eager path (``nn.Sequential`` of Linear/ReLU, in ``field_heads.py``) stays the CPU path and the
reference. Eagerly, a head is 3 matmuls, 3 bias adds and 2 ReLUs forward, and about twice that
backward, each a launch that writes an (N, 64) activation to memory and reads it back; over the
millions of samples of a NeRF step that traffic, and the launches, are most of the MLP's time
(H200 profile: matmuls, ReLUs, their backward and the bias-gradient sums ≈ 40 % of a NeRF step's
GPU time). Here a block of rows goes through a whole head in registers:

- forward: one launch for both heads, one block of rows per program, the features read once;
- backward: one launch, a fixed number of programs per head (``_programs``), each looping over
  blocks of rows. It recomputes the block's pre-activations (cheaper than storing them), then
  the gradients layer by layer. Weight and bias gradients are summed in registers across the
  program's blocks and written as one partial per program; ``torch.sum`` over the partials
  gives the parameter gradients, deterministically for a given row count and device. The
  feature gradient is the sum of the two heads' contributions. Both add atomically into a zeroed
  buffer; two addends from zero give the same float in either order, so this is deterministic too.

Products are TF32 (inputs rounded to 10-bit mantissas, fp32 accumulation), whatever PyTorch's
``allow_tf32`` says: tcnn runs these MLPs in fp16, and on the H200 the fp32-exact alternative
(``tf32x3``) was slower than the eager modules (``benchmarks/results/field_speed_h200_heads.md``),
so the kernels would have no reason to exist in full fp32. ``execution.field_mlp=eager`` gives the fp32
modules back. The interpreter computes in fp32. Sizes: widths up to 128, outputs up to 16, padded
to powers of two ≥ 16 with masked loads (no packed copies of the weights).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import torch
from torch import Tensor

from morpheus_core.runtime.triton_support import device_guard, interpreting, load_triton

triton, tl, _jit = load_triton()

MAX_WIDTH = 128
MAX_OUT = 16
_FORWARD_BLOCK = 128
_BACKWARD_BLOCK = 64
_FORWARD_WARPS = 4
_BACKWARD_WARPS = 4
_PROGRAMS_PER_SM = 8
_WEIGHT_GRADS = "fused"
"""How the backward sums the weight gradients over the rows: ``fused`` (a fixed number of programs,
each summing its blocks in registers into one partial) or ``gemm`` (one program per block of rows
stores the block's hidden activations and their gradients, 4 × hidden floats per row and head, and
matmuls sum Hᵀ·dZ over all rows, as tcnn's fully fused MLP does). On the H200 the fused backward
takes ~7× its forward (``field_heads_h200_gradx.md``); ``gemm`` is the candidate to replace it, not yet
timed on a GPU: ``benchmarks/field_heads_kernel.py`` times both."""
_GRAD_X = "store"
"""How the two heads' feature gradients meet: ``store`` (each head stores its own into one half of a
(2, N, in) buffer, summed after), ``relaxed`` or ``acq_rel`` (both add into one zeroed buffer with
atomics of that memory order). ``benchmarks/field_heads_kernel.py`` compares them."""

# Integer arguments that change from call to call: Triton would otherwise compile a variant for each
# combination of "divisible by 16" and "equal to 1" it meets (seconds each, mid-run; H200: a NeRF
# batch of 4, whose sample counts vary every step, spent its first steps compiling).
_VARYING = ("n_rows", "n_tiles", "n_programs", "first_head")
_VARYING_FORWARD = ("n_rows",)

Head = Sequence[Tensor]
"""One head's parameters: (w1, b1, w2, b2, w3, b3), weights in ``nn.Linear``'s (out, in) layout."""


def supports(feats: Tensor, heads: Sequence[Head]) -> bool:
    """Whether these kernels take these inputs: fp32 (N, in) features and fp32 heads of in → h → h →
    out with in, h ≤ 128 and out ≤ 16, every tensor on the features' device."""
    if feats.dtype != torch.float32 or feats.dim() != 2:
        return False
    n_in = feats.shape[1]
    for head in heads:
        if len(head) != 6 or any(p.dtype != torch.float32 or p.device != feats.device for p in head):
            return False
        w1, b1, w2, b2, w3, b3 = head
        h, o = w1.shape[0], w3.shape[0]
        if (w1.shape != (h, n_in) or w2.shape != (h, h) or w3.shape != (o, h) or b1.shape != (h,)
                or b2.shape != (h,) or b3.shape != (o,) or not (0 < n_in <= MAX_WIDTH and 0 < h <= MAX_WIDTH
                                                                and 0 < o <= MAX_OUT)):
            return False
    return len({head[0].shape[0] for head in heads}) == 1


@_jit
def _weight(ptr, n_out, n_in, OUT: tl.constexpr, IN: tl.constexpr):
    """A Linear weight (n_out, n_in) as an (OUT, IN) tile, zero outside the matrix."""
    o = tl.arange(0, OUT)
    i = tl.arange(0, IN)
    return tl.load(ptr + o[:, None] * n_in + i[None, :], mask=(o[:, None] < n_out) & (i[None, :] < n_in), other=0.0)


@_jit
def _bias(ptr, n, N: tl.constexpr):
    offs = tl.arange(0, N)
    return tl.load(ptr + offs, mask=offs < n, other=0.0)


@_jit
def _rows(x_ptr, tile, n_rows, n_in, IN: tl.constexpr, BLOCK: tl.constexpr):
    """Row indices, their validity and the (BLOCK, IN) features of block ``tile``."""
    rows = (tile * BLOCK + tl.arange(0, BLOCK)).to(tl.int64)
    valid = rows < n_rows
    cols = tl.arange(0, IN)
    x = tl.load(x_ptr + rows[:, None] * n_in + cols[None, :], mask=valid[:, None] & (cols[None, :] < n_in), other=0.0)
    return rows, valid, x


@_jit
def _pre_activations(x, w1, b1, w2, b2, n_in, n_hidden, IN: tl.constexpr, HID: tl.constexpr, PREC: tl.constexpr):
    """The two hidden layers' pre-activations a1, a2 (BLOCK, HID), and the weights read for them."""
    W1 = _weight(w1, n_hidden, n_in, HID, IN)
    W2 = _weight(w2, n_hidden, n_hidden, HID, HID)
    a1 = tl.dot(x, tl.trans(W1), input_precision=PREC) + _bias(b1, n_hidden, HID)[None, :]
    a2 = tl.dot(tl.maximum(a1, 0.0), tl.trans(W2), input_precision=PREC) + _bias(b2, n_hidden, HID)[None, :]
    return a1, a2, W1, W2


@_jit
def _forward_head(x, rows, valid, w1, b1, w2, b2, w3, b3, out_ptr, n_in, n_hidden, n_out,
                  IN: tl.constexpr, HID: tl.constexpr, OUT: tl.constexpr, PREC: tl.constexpr):
    _a1, a2, _W1, _W2 = _pre_activations(x, w1, b1, w2, b2, n_in, n_hidden, IN, HID, PREC)
    W3 = _weight(w3, n_out, n_hidden, OUT, HID)
    y = tl.dot(tl.maximum(a2, 0.0), tl.trans(W3), input_precision=PREC) + _bias(b3, n_out, OUT)[None, :]
    o = tl.arange(0, OUT)
    tl.store(out_ptr + rows[:, None] * n_out + o[None, :], y, mask=valid[:, None] & (o[None, :] < n_out))


@_jit(do_not_specialize=_VARYING_FORWARD)
def _forward_kernel(x_ptr, dw1, db1, dw2, db2, dw3, db3, d_out, aw1, ab1, aw2, ab2, aw3, ab3, a_out,
                    n_rows, n_in, n_hidden, n_out_a, IN: tl.constexpr, HID: tl.constexpr, OUT: tl.constexpr,
                    BLOCK: tl.constexpr, ALBEDO: tl.constexpr, PREC: tl.constexpr):
    rows, valid, x = _rows(x_ptr, tl.program_id(0), n_rows, n_in, IN, BLOCK)
    _forward_head(x, rows, valid, dw1, db1, dw2, db2, dw3, db3, d_out, n_in, n_hidden, 1, IN, HID, OUT, PREC)
    if ALBEDO:
        _forward_head(x, rows, valid, aw1, ab1, aw2, ab2, aw3, ab3, a_out, n_in, n_hidden, n_out_a,
                      IN, HID, OUT, PREC)


@_jit
def _store_matrix(ptr, acc_t, n_out, n_in, OUT: tl.constexpr, IN: tl.constexpr):
    """Store an (IN, OUT) accumulator of Wᵀ's gradient into W's (n_out, n_in) layout."""
    i = tl.arange(0, IN)
    o = tl.arange(0, OUT)
    tl.store(ptr + o[None, :] * n_in + i[:, None], acc_t, mask=(o[None, :] < n_out) & (i[:, None] < n_in))


@_jit
def _store_vector(ptr, acc, n, N: tl.constexpr):
    offs = tl.arange(0, N)
    tl.store(ptr + offs, acc, mask=offs < n)


@_jit
def _backward_head(x_ptr, g_ptr, gx_ptr, part_ptr, w1, b1, w2, b2, w3, b3, n_rows, n_in, n_hidden, n_out,
                   n_tiles, n_programs, IN: tl.constexpr, HID: tl.constexpr, OUT: tl.constexpr,
                   BLOCK: tl.constexpr, WANT_X: tl.constexpr, PREC: tl.constexpr, GX: tl.constexpr):
    pid = tl.program_id(0)
    acc_w1 = tl.zeros([IN, HID], dtype=tl.float32)
    acc_b1 = tl.zeros([HID], dtype=tl.float32)
    acc_w2 = tl.zeros([HID, HID], dtype=tl.float32)
    acc_b2 = tl.zeros([HID], dtype=tl.float32)
    acc_w3 = tl.zeros([HID, OUT], dtype=tl.float32)
    acc_b3 = tl.zeros([OUT], dtype=tl.float32)
    o = tl.arange(0, OUT)
    for tile in range(pid, n_tiles, n_programs):
        rows, valid, x = _rows(x_ptr, tile, n_rows, n_in, IN, BLOCK)
        a1, a2, W1, W2 = _pre_activations(x, w1, b1, w2, b2, n_in, n_hidden, IN, HID, PREC)
        W3 = _weight(w3, n_out, n_hidden, OUT, HID)
        g = tl.load(g_ptr + rows[:, None] * n_out + o[None, :], mask=valid[:, None] & (o[None, :] < n_out), other=0.0)
        h1 = tl.maximum(a1, 0.0)
        h2 = tl.maximum(a2, 0.0)
        acc_w3 += tl.dot(tl.trans(h2), g, input_precision=PREC)
        acc_b3 += tl.sum(g, 0)
        dz2 = tl.where(a2 > 0.0, tl.dot(g, W3, input_precision=PREC), 0.0)
        acc_w2 += tl.dot(tl.trans(h1), dz2, input_precision=PREC)
        acc_b2 += tl.sum(dz2, 0)
        dz1 = tl.where(a1 > 0.0, tl.dot(dz2, W2, input_precision=PREC), 0.0)
        acc_w1 += tl.dot(tl.trans(x), dz1, input_precision=PREC)
        acc_b1 += tl.sum(dz1, 0)
        if WANT_X:
            cols = tl.arange(0, IN)
            dx = tl.dot(dz1, W1, input_precision=PREC)
            gx_mask = valid[:, None] & (cols[None, :] < n_in)
            if GX == "store":
                tl.store(gx_ptr + rows[:, None] * n_in + cols[None, :], dx, mask=gx_mask)
            elif GX == "relaxed":
                tl.atomic_add(gx_ptr + rows[:, None] * n_in + cols[None, :], dx, mask=gx_mask, sem="relaxed")
            else:
                tl.atomic_add(gx_ptr + rows[:, None] * n_in + cols[None, :], dx, mask=gx_mask)
    # One partial per program, in the parameters' order and layouts (see _layout).
    base = part_ptr + pid.to(tl.int64) * (n_hidden * n_in + n_hidden * n_hidden + n_out * n_hidden
                                          + 2 * n_hidden + n_out)
    _store_matrix(base, acc_w1, n_hidden, n_in, HID, IN)
    base += n_hidden * n_in
    _store_vector(base, acc_b1, n_hidden, HID)
    base += n_hidden
    _store_matrix(base, acc_w2, n_hidden, n_hidden, HID, HID)
    base += n_hidden * n_hidden
    _store_vector(base, acc_b2, n_hidden, HID)
    base += n_hidden
    _store_matrix(base, acc_w3, n_out, n_hidden, OUT, HID)
    base += n_out * n_hidden
    _store_vector(base, acc_b3, n_out, OUT)


@_jit(do_not_specialize=_VARYING)
def _backward_kernel(x_ptr, gx_ptr, dw1, db1, dw2, db2, dw3, db3, d_grad, d_part, aw1, ab1, aw2, ab2, aw3, ab3,
                     a_grad, a_part, n_rows, n_in, n_hidden, n_out_a, n_tiles, n_programs, first_head,
                     IN: tl.constexpr, HID: tl.constexpr, OUT: tl.constexpr, BLOCK: tl.constexpr,
                     WANT_X: tl.constexpr, PREC: tl.constexpr, GX: tl.constexpr):
    if tl.program_id(1) + first_head == 0:
        _backward_head(x_ptr, d_grad, gx_ptr, d_part, dw1, db1, dw2, db2, dw3, db3, n_rows, n_in, n_hidden, 1,
                       n_tiles, n_programs, IN, HID, OUT, BLOCK, WANT_X, PREC, GX)
    else:
        # Under "store" with both heads, the albedo head writes the second half of the (2, N, in) buffer.
        gx_a = gx_ptr + tl.program_id(1).to(tl.int64) * n_rows * n_in if GX == "store" else gx_ptr
        _backward_head(x_ptr, a_grad, gx_a, a_part, aw1, ab1, aw2, ab2, aw3, ab3, n_rows, n_in, n_hidden, n_out_a,
                       n_tiles, n_programs, IN, HID, OUT, BLOCK, WANT_X, PREC, GX)


@_jit
def _row_grads_head(x_ptr, g_ptr, gx_ptr, act_ptr, w1, b1, w2, b2, w3, b3, n_rows, n_in, n_hidden, n_out,
                    IN: tl.constexpr, HID: tl.constexpr, OUT: tl.constexpr, BLOCK: tl.constexpr,
                    WANT_X: tl.constexpr, PREC: tl.constexpr):
    """One block of rows: store h1, h2, dz1, dz2 (the planes of ``act_ptr``) and the feature gradient."""
    rows, valid, x = _rows(x_ptr, tl.program_id(0), n_rows, n_in, IN, BLOCK)
    a1, a2, W1, W2 = _pre_activations(x, w1, b1, w2, b2, n_in, n_hidden, IN, HID, PREC)
    W3 = _weight(w3, n_out, n_hidden, OUT, HID)
    o = tl.arange(0, OUT)
    g = tl.load(g_ptr + rows[:, None] * n_out + o[None, :], mask=valid[:, None] & (o[None, :] < n_out), other=0.0)
    dz2 = tl.where(a2 > 0.0, tl.dot(g, W3, input_precision=PREC), 0.0)
    dz1 = tl.where(a1 > 0.0, tl.dot(dz2, W2, input_precision=PREC), 0.0)
    h = tl.arange(0, HID)
    offs = rows[:, None] * n_hidden + h[None, :]
    mask = valid[:, None] & (h[None, :] < n_hidden)
    plane = n_rows.to(tl.int64) * n_hidden
    tl.store(act_ptr + offs, tl.maximum(a1, 0.0), mask=mask)
    tl.store(act_ptr + plane + offs, tl.maximum(a2, 0.0), mask=mask)
    tl.store(act_ptr + 2 * plane + offs, dz1, mask=mask)
    tl.store(act_ptr + 3 * plane + offs, dz2, mask=mask)
    if WANT_X:
        cols = tl.arange(0, IN)
        dx = tl.dot(dz1, W1, input_precision=PREC)
        tl.store(gx_ptr + rows[:, None] * n_in + cols[None, :], dx, mask=valid[:, None] & (cols[None, :] < n_in))


@_jit(do_not_specialize=("n_rows", "first_head"))
def _row_grads_kernel(x_ptr, gx_ptr, dw1, db1, dw2, db2, dw3, db3, d_grad, d_act, aw1, ab1, aw2, ab2, aw3, ab3,
                      a_grad, a_act, n_rows, n_in, n_hidden, n_out_a, first_head, IN: tl.constexpr,
                      HID: tl.constexpr, OUT: tl.constexpr, BLOCK: tl.constexpr, WANT_X: tl.constexpr,
                      PREC: tl.constexpr):
    if tl.program_id(1) + first_head == 0:
        _row_grads_head(x_ptr, d_grad, gx_ptr, d_act, dw1, db1, dw2, db2, dw3, db3, n_rows, n_in, n_hidden, 1,
                        IN, HID, OUT, BLOCK, WANT_X, PREC)
    else:
        gx_a = gx_ptr + tl.program_id(1).to(tl.int64) * n_rows * n_in  # both heads: the second half
        _row_grads_head(x_ptr, a_grad, gx_a, a_act, aw1, ab1, aw2, ab2, aw3, ab3, n_rows, n_in, n_hidden,
                        n_out_a, IN, HID, OUT, BLOCK, WANT_X, PREC)


def _pad(n: int) -> int:
    return max(16, triton.next_power_of_2(n))


@functools.cache
def _sm_count(index: int) -> int:
    return torch.cuda.get_device_properties(index).multi_processor_count


def _programs(feats: Tensor, n_tiles: int) -> int:
    """Backward programs per head: a few per SM keep the GPU busy; fewer programs mean fewer partials."""
    if interpreting() or feats.device.type != "cuda":
        return max(1, min(n_tiles, 4))
    per_device = _PROGRAMS_PER_SM * _sm_count(feats.device.index or 0)
    return max(1, min(n_tiles, per_device))


def _layout(head: Head) -> list[int]:
    return [p.numel() for p in head]


def _contiguous(head: Head) -> list[Tensor]:
    return [p.contiguous() for p in head]


def heads_forward(feats: Tensor, density: Head, albedo: Head | None) -> tuple[Tensor, Tensor | None]:
    """(N, in) features → the density head's (N, 1) and the albedo head's (N, out) raw outputs (fp32),
    as ``density_mlp(feats)`` and ``albedo_mlp(feats)``; the albedo is None when ``albedo`` is."""
    heads = [density] if albedo is None else [density, albedo]
    if not supports(feats, heads):
        raise ValueError("the fused field heads take fp32 (N, in) features and two-hidden-layer fp32 heads "
                         f"of width ≤ {MAX_WIDTH}, output ≤ {MAX_OUT}, on the features' device")
    feats = feats.contiguous()
    d = _contiguous(density)
    a = _contiguous(albedo) if albedo is not None else d
    n, n_in = feats.shape
    n_hidden, n_out_a = d[0].shape[0], a[4].shape[0]
    d_out = feats.new_empty((n, 1))
    a_out = feats.new_empty((n, n_out_a)) if albedo is not None else d_out
    if n > 0:
        with device_guard(feats):
            _forward_kernel[(triton.cdiv(n, _FORWARD_BLOCK),)](
                feats, *d, d_out, *a, a_out, n, n_in, n_hidden, n_out_a, IN=_pad(n_in), HID=_pad(n_hidden),
                OUT=MAX_OUT, BLOCK=_FORWARD_BLOCK, ALBEDO=albedo is not None, PREC="tf32",
                num_warps=_FORWARD_WARPS)
    return d_out, (a_out if albedo is not None else None)


def heads_backward(feats: Tensor, density: Head, albedo: Head | None, grad_density: Tensor | None,
                   grad_albedo: Tensor | None, want_x: bool) -> tuple[Tensor | None, list[Tensor] | None,
                                                                     list[Tensor] | None]:
    """(grad_feats, density parameter grads, albedo parameter grads) from the outputs' gradients.

    A head whose output gradient is None gets None (nothing launched for it); grad_feats is None
    unless ``want_x``."""
    heads = [density] if albedo is None else [density, albedo]
    if not supports(feats, heads):
        raise ValueError("heads_backward: inputs the fused field heads do not take (see supports)")
    if grad_albedo is not None and albedo is None:
        raise ValueError("an albedo gradient without an albedo head")
    feats = feats.contiguous()
    d = _contiguous(density)
    a = _contiguous(albedo) if albedo is not None else d
    n, n_in = feats.shape
    n_hidden, n_out_a = d[0].shape[0], a[4].shape[0]
    wanted = [grad_density is not None, grad_albedo is not None]
    if not any(wanted):
        return None, None, None
    if _WEIGHT_GRADS == "gemm":
        return _backward_gemm(feats, d, a, grad_density, grad_albedo, want_x)
    both = all(wanted)
    if not want_x:
        gx = None
    elif _GRAD_X == "store":  # every row is written: the buffer needs no zeros
        gx = feats.new_empty((2, n, n_in)) if both else feats.new_empty((n, n_in))
    else:
        gx = feats.new_zeros((n, n_in))
    n_tiles = triton.cdiv(n, _BACKWARD_BLOCK) if n > 0 else 0
    programs = _programs(feats, n_tiles)
    d_grad = grad_density.contiguous().float() if grad_density is not None else feats
    a_grad = grad_albedo.contiguous().float() if grad_albedo is not None else feats
    d_part = feats.new_zeros((programs, sum(_layout(d)))) if wanted[0] else feats
    a_part = feats.new_zeros((programs, sum(_layout(a)))) if wanted[1] else feats
    if n_tiles > 0:
        first = 0 if wanted[0] else 1
        with device_guard(feats):
            _backward_kernel[(programs, sum(wanted))](
                feats, gx if gx is not None else feats, *d, d_grad, d_part, *a, a_grad, a_part,
                n, n_in, n_hidden, n_out_a, n_tiles, programs, first, IN=_pad(n_in), HID=_pad(n_hidden),
                OUT=MAX_OUT, BLOCK=_BACKWARD_BLOCK, WANT_X=gx is not None, PREC="tf32", GX=_GRAD_X,
                num_warps=_BACKWARD_WARPS)
    grad_x = gx[0] + gx[1] if gx is not None and gx.dim() == 3 else gx

    def unpack(part: Tensor, head: list[Tensor]) -> list[Tensor]:
        flat = part.sum(0)
        return [g.view_as(p) for g, p in zip(flat.split(_layout(head)), head, strict=True)]

    return (grad_x, unpack(d_part, d) if wanted[0] else None,
            unpack(a_part, a) if wanted[1] else None)


def _backward_gemm(feats: Tensor, d: list[Tensor], a: list[Tensor], grad_density: Tensor | None,
                   grad_albedo: Tensor | None, want_x: bool) -> tuple[Tensor | None, list[Tensor] | None,
                                                                     list[Tensor] | None]:
    """``heads_backward`` with the weight gradients as matmuls over all rows (``_WEIGHT_GRADS = "gemm"``)."""
    n, n_in = feats.shape
    n_hidden = d[0].shape[0]
    grads = [g.contiguous().float() if g is not None else None for g in (grad_density, grad_albedo)]
    wanted = [g is not None for g in grads]
    acts = [feats.new_empty((4, n, n_hidden)) if w else feats for w in wanted]
    gx = feats.new_empty((sum(wanted), n, n_in) if sum(wanted) > 1 else (n, n_in)) if want_x else None
    if n > 0:
        with device_guard(feats):
            _row_grads_kernel[(triton.cdiv(n, _BACKWARD_BLOCK), sum(wanted))](
                feats, gx if gx is not None else feats, *d, grads[0] if wanted[0] else feats, acts[0], *a,
                grads[1] if wanted[1] else feats, acts[1], n, n_in, n_hidden, a[4].shape[0], 0 if wanted[0] else 1,
                IN=_pad(n_in), HID=_pad(n_hidden), OUT=MAX_OUT, BLOCK=_BACKWARD_BLOCK, WANT_X=gx is not None,
                PREC="tf32", num_warps=_BACKWARD_WARPS)

    def head_grads(g: Tensor, act: Tensor) -> list[Tensor]:
        h1, h2, dz1, dz2 = act
        return [dz1.T @ feats, dz1.sum(0), dz2.T @ h1, dz2.sum(0), g.T @ h2, g.sum(0)]

    grad_x = gx[0] + gx[1] if gx is not None and gx.dim() == 3 else gx
    return (grad_x, *(head_grads(g, act) if g is not None else None for g, act in zip(grads, acts, strict=True)))
