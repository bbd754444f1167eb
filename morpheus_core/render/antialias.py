"""Silhouette anti-aliasing for the rasteriser (``morpheus_core.render.raster``), edge-based and differentiable.

``silhouette_crossings`` finds the crossings, ``antialias`` blends with them. The hard coverage is a
step function of the vertex positions; its gradient is zero. We find the mesh edges that can
form the silhouette in each view (boundary / non-manifold edges, and edges whose two faces have
opposite screen orientation or only one of them drawn) and walk each one like a line rasteriser
along its major axis: at every pixel column (for a mostly horizontal edge; rows otherwise) the
edge crosses the segment between two vertically (horizontally) adjacent pixel centres at an
analytic position ``t`` (in pixels, measured from the covered centre), computed from the
differentiable projected end points. Only pairs with exactly one covered pixel keep a crossing;
if several edges cross one pair, the one nearest the uncovered pixel (largest ``t``) bounds the
covered interval and wins. Reading the pair as two unit boxes split at ``t``, the covered pixel
keeps ``min(t + ½, 1)`` of its own value and the uncovered pixel takes ``max(t − ½, 0)`` of the
covered one; ``antialias`` applies exactly that blend to any image (mask, colour, ...).
Why this gives the right gradient: the covered mass of a pair is ``t + ½``, so ``d(mass)/dt = 1``;
an edge of length L whose normal moves by δ crosses ``L·|cos θ|`` columns (major-axis walk) and
shifts each crossing by ``δ/|cos θ|``, so the soft area changes by ``L·δ`` — the expected change
of the hard pixel count. Walking only one axis per edge avoids counting it twice. Because the
crossings come from the silhouette *edges*, not from the pixel's own triangle, this holds on
dense meshes whose triangles are smaller than a pixel (nvdiffrast-style blending, which only
looks at the triangle covering a pixel centre, gives almost no gradient there).
Limitations: only coverage silhouettes against empty pixels are anti-aliased (occlusion edges
inside the object are not), and edges of culled (near-plane) triangles give no crossings.

Pixel coordinates, clip space and the ``RasterConfig`` limits are those of ``render.raster``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from morpheus_core.gather import gather_batched_rows, gather_rows
from morpheus_core.render.raster import Fragments, RasterInputError, _pair_chunks, _span, _to_pixels

# Resolution of the crossing position t in the (t, edge) key that picks the outermost edge of a pair.
_T_BITS = 20


@dataclass
class SilhouetteCrossings:
    """Pixel pairs across the silhouette: flat indices (P,) of the covered (``inner``) and empty
    (``outer``) pixel, and ``t`` (P,) — where the silhouette edge crosses the segment between their
    centres, in pixels from the covered one, in [0, 1], differentiable w.r.t. the clip vertices."""

    inner: Tensor
    outer: Tensor
    t: Tensor


def silhouette_crossings(fragments: Fragments) -> SilhouetteCrossings:
    """Find where silhouette edges cross covered/empty pixel pairs (see the module docstring)."""
    config = fragments.config
    clip, height, width, batch = fragments.clip, fragments.height, fragments.width, fragments.batch
    hw = height * width
    topo = fragments.edges
    device = clip.device
    with torch.no_grad():
        orient = fragments.orientation  # (B, F)
        has_two = topo.faces[:, 1] >= 0
        o1 = orient[:, topo.faces[:, 0]]
        o2 = torch.where(has_two, orient[:, topo.faces[:, 1].clamp(min=0)], 0)
        candidate = ((o1 != 0) | (o2 != 0)) & (topo.nonmanifold | ~has_two | (o1 != o2))
        sx, sy, _, ok = _to_pixels(clip.detach(), height, width, config.near_w)
        candidate &= ok[:, topo.vertices].all(-1)
        view, edge = candidate.nonzero(as_tuple=True)
        u0, u1 = sx[view, topo.vertices[edge, 0]], sx[view, topo.vertices[edge, 1]]
        v0, v1 = sy[view, topo.vertices[edge, 0]], sy[view, topo.vertices[edge, 1]]
        du, dv = u1 - u0, v1 - v0
        long_enough = torch.maximum(du.abs(), dv.abs()) > config.min_edge_px
        x_major = du.abs() >= dv.abs()
        covered = fragments.face_id.reshape(-1) >= 0
        best = torch.full((2 * batch * hw,), -1, dtype=torch.int64, device=device)
        edge_bits = max(1, topo.vertices.shape[0].bit_length())
        # Walk x-major edges along columns (crossing vertical pixel pairs) and y-major edges along rows.
        for major in (True, False):
            sel = (x_major == major) & long_enough
            a0, a1 = (u0, u1) if major else (v0, v1)
            c0, c1 = (v0, v1) if major else (u0, u1)
            n_along, n_across = (width, height) if major else (height, width)
            first, last = _span(torch.minimum(a0, a1), torch.maximum(a0, a1), n_along)
            counts = ((last - first + 1).clamp(min=0) * sel).long()
            for owner, local in _pair_chunks(counts, config.max_pairs_per_chunk):
                along = first[owner] + local
                slope = (c1[owner] - c0[owner]) / (a1[owner] - a0[owner])
                cross = c0[owner] + (along.to(slope.dtype) - a0[owner]) * slope
                lower = torch.floor(cross.clamp(-1.0, float(n_across))).long()
                inside = (lower >= 0) & (lower <= n_across - 2)
                lower = lower.clamp(0, max(n_across - 2, 0))
                row, col = (lower, along) if major else (along, lower)
                p = view[owner] * hw + row * width + col
                q = p + (width if major else 1)
                cov_p, cov_q = covered[p], covered[q]
                keep = inside & (cov_p != cov_q)
                frac = cross - lower.to(cross.dtype)
                t = torch.where(cov_p, frac, 1.0 - frac).clamp(0.0, 1.0)
                key = ((t * ((1 << _T_BITS) - 1)).round().long() << edge_bits) | edge[owner]
                pair = p + (0 if major else batch * hw)
                best.scatter_reduce_(0, pair, torch.where(keep, key, -1), reduce="amax", include_self=True)
        pair = (best >= 0).nonzero().squeeze(1)
        win_edge = best[pair] & ((1 << edge_bits) - 1)
        vertical = pair < batch * hw
        p = pair % (batch * hw)
        q = p + torch.where(vertical, width, 1)
        cov_p = covered[p]
        win_view = p // hw

    # Differentiable recomputation of t for the winning edge of each pair.
    ends = gather_batched_rows(clip, win_view.unsqueeze(-1), topo.vertices[win_edge])  # (P, 2, 4)
    w = ends[..., 3]
    ex = (ends[..., 0] / w + 1.0) * (0.5 * width) - 0.5
    ey = (1.0 - ends[..., 1] / w) * (0.5 * height) - 0.5
    row = ((p % hw) // width).to(clip.dtype)
    col = (p % width).to(clip.dtype)
    a0 = torch.where(vertical, ex[:, 0], ey[:, 0])
    a1 = torch.where(vertical, ex[:, 1], ey[:, 1])
    c0 = torch.where(vertical, ey[:, 0], ex[:, 0])
    c1 = torch.where(vertical, ey[:, 1], ex[:, 1])
    along = torch.where(vertical, col, row)
    lower = torch.where(vertical, row, col)
    frac = c0 + (along - a0) * (c1 - c0) / (a1 - a0) - lower
    t = torch.where(cov_p, frac, 1.0 - frac).clamp(0.0, 1.0)
    inner = torch.where(cov_p, p, q)
    outer = torch.where(cov_p, q, p)
    return SilhouetteCrossings(inner=inner, outer=outer, t=t)


def antialias(image: Tensor, fragments: Fragments, crossings: SilhouetteCrossings | None = None) -> Tensor:
    """Blend ``image`` (B, H, W, C) across silhouette pixel pairs by their analytic coverage.

    The covered pixel moves ``max(½ − t, 0)`` of the way to its empty neighbour's value and the empty
    pixel ``max(t − ½, 0)`` of the way to the covered one's; a pixel in several pairs has its weights
    summed and, if the sum exceeds 1, normalised. Pass ``crossings`` to reuse them across images."""
    batch, height, width = fragments.batch, fragments.height, fragments.width
    if image.dim() != 4 or tuple(image.shape[:3]) != (batch, height, width):
        raise RasterInputError(f"image must be ({batch}, {height}, {width}, C), got {tuple(image.shape)}")
    crossings = crossings if crossings is not None else silhouette_crossings(fragments)
    flat = image.reshape(batch * height * width, image.shape[-1])
    t = crossings.t.to(flat.dtype)
    w_in = torch.relu(0.5 - t)
    w_out = torch.relu(t - 0.5)
    inner, outer = gather_rows(flat, crossings.inner), gather_rows(flat, crossings.outer)
    pull = torch.zeros_like(flat).index_add(0, crossings.inner, w_in.unsqueeze(-1) * (outer - inner))
    pull = pull.index_add(0, crossings.outer, w_out.unsqueeze(-1) * (inner - outer))
    weight = flat.new_zeros(flat.shape[0]).index_add(0, crossings.inner, w_in).index_add(0, crossings.outer, w_out)
    out = flat + pull / weight.clamp(min=1.0).unsqueeze(-1)
    return out.reshape(image.shape)
