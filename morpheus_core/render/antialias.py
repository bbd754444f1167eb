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

from morpheus_core.render.raster import Fragments, RasterInputError, clip_to_pixels, pair_chunks, pixel_span
from morpheus_core.runtime.devices import compiled_for
from morpheus_core.runtime.gather import gather_batched_rows, gather_rows

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


def _candidates(orient: Tensor, edge_faces: Tensor, nonmanifold: Tensor, edge_vertices: Tensor, clip: Tensor,
                height: int, width: int, near_w: float) -> tuple[Tensor, Tensor, Tensor]:
    """(B, E) flags of the edges that can form a view's silhouette, and the vertices' pixel
    coordinates sx, sy (B, V). Pure tensor code: compiled on CUDA (``compiled_for``)."""
    has_two = edge_faces[:, 1] >= 0
    o1 = orient[:, edge_faces[:, 0]]
    o2 = torch.where(has_two, orient[:, edge_faces[:, 1].clamp(min=0)], 0)
    candidate = ((o1 != 0) | (o2 != 0)) & (nonmanifold | ~has_two | (o1 != o2))
    sx, sy, _, ok = clip_to_pixels(clip, height, width, near_w)
    return candidate & ok[:, edge_vertices].all(-1), sx, sy


def _walks(view: Tensor, edge: Tensor, edge_vertices: Tensor, sx: Tensor, sy: Tensor, height: int, width: int,
           min_edge_px: float) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Per candidate (view, edge): its screen end points ``ends`` (n, 4: u0, u1, v0, v1), and the first
    pixel and pixel count of its walk along columns (x-major edges; 0 for the others) and along rows
    (y-major edges). Pure tensor code: compiled on CUDA."""
    ia, ib = edge_vertices[edge, 0], edge_vertices[edge, 1]
    u0, u1, v0, v1 = sx[view, ia], sx[view, ib], sy[view, ia], sy[view, ib]
    du, dv = u1 - u0, v1 - v0
    long_enough = torch.maximum(du.abs(), dv.abs()) > min_edge_px
    x_major = du.abs() >= dv.abs()
    first_x, last_x = pixel_span(torch.minimum(u0, u1), torch.maximum(u0, u1), width)
    first_y, last_y = pixel_span(torch.minimum(v0, v1), torch.maximum(v0, v1), height)
    counts_x = ((last_x - first_x + 1).clamp(min=0) * (x_major & long_enough)).long()
    counts_y = ((last_y - first_y + 1).clamp(min=0) * (~x_major & long_enough)).long()
    return torch.stack([u0, u1, v0, v1], -1), first_x, counts_x, first_y, counts_y


def _crossing_keys(owner: Tensor, local: Tensor, first: Tensor, ends: Tensor, view: Tensor, edge: Tensor,
                   covered: Tensor, major: bool, width: int, hw: int, n_across: int, offset: int,
                   edge_scale: int) -> tuple[Tensor, Tensor]:
    """Pair slot (P,) and packed (t, edge) key (P,) of each (walk, k-th step) pair; pairs that do not
    separate a covered from an empty pixel get the neutral key -1. ``edge_scale`` = 2^edge_bits (a
    product, not a shift: dynamo in torch 2.11 cannot shift by a symbolic int). Pure tensor code:
    compiled on CUDA."""
    e = ends[owner]
    a0, a1, c0, c1 = (e[:, 0], e[:, 1], e[:, 2], e[:, 3]) if major else (e[:, 2], e[:, 3], e[:, 0], e[:, 1])
    along = first[owner] + local
    slope = (c1 - c0) / (a1 - a0)
    cross = c0 + (along.to(slope.dtype) - a0) * slope
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
    key = (t * ((1 << _T_BITS) - 1)).round().long() * edge_scale + edge[owner]
    return p + offset, torch.where(keep, key, -1)


def _crossings(pair: Tensor, best: Tensor, covered: Tensor, edge_vertices: Tensor, clip: Tensor, height: int,
               width: int, edge_scale: int) -> tuple[Tensor, Tensor, Tensor]:
    """Differentiable t (P,) of each pair's winning edge, recomputed from the clip vertices, and the
    pair's inner (covered) and outer pixels. Pure tensor code: compiled on CUDA."""
    hw = height * width
    batch_hw = covered.shape[0]
    win_edge = best[pair] % edge_scale  # the kept keys are ≥ 0
    vertical = pair < batch_hw
    p = pair % batch_hw
    q = p + torch.where(vertical, width, 1)
    cov_p = covered[p]
    ends = gather_batched_rows(clip, (p // hw).unsqueeze(-1), edge_vertices[win_edge])  # (P, 2, 4)
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
    return t, torch.where(cov_p, p, q), torch.where(cov_p, q, p)


def silhouette_crossings(fragments: Fragments) -> SilhouetteCrossings:
    """Find where silhouette edges cross covered/empty pixel pairs (see the module docstring)."""
    config = fragments.config
    clip, height, width = fragments.clip, fragments.height, fragments.width
    topo = fragments.edges
    device = clip.device
    with torch.no_grad():
        candidate, sx, sy = compiled_for(_candidates, device)(
            fragments.orientation, topo.edge_faces, topo.nonmanifold, topo.edge_vertices, clip.detach(), height, width,
            config.near_w)
        view, edge = candidate.nonzero(as_tuple=True)
        ends, first_x, counts_x, first_y, counts_y = compiled_for(_walks, device)(
            view, edge, topo.edge_vertices, sx, sy, height, width, config.min_edge_px)
        covered = fragments.face_id.reshape(-1) >= 0
        best = torch.full((2 * covered.shape[0],), -1, dtype=torch.int64, device=device)
        edge_scale = 1 << max(1, topo.edge_vertices.shape[0].bit_length())
        # Walk x-major edges along columns (crossing vertical pixel pairs) and y-major edges along rows;
        # the row walks' pairs sit in the second half of ``best``.
        for major, first, counts in ((True, first_x, counts_x), (False, first_y, counts_y)):
            for owner, local in pair_chunks(counts, config.max_pairs_per_chunk):
                pair, key = compiled_for(_crossing_keys, device)(
                    owner, local, first, ends, view, edge, covered, major, width, height * width,
                    height if major else width, 0 if major else covered.shape[0], edge_scale)
                best.scatter_reduce_(0, pair, key, reduce="amax", include_self=True)
        pair = (best >= 0).nonzero().squeeze(1)
    t, inner, outer = compiled_for(_crossings, device)(pair, best, covered, topo.edge_vertices, clip, height, width,
                                                        edge_scale)
    return SilhouetteCrossings(inner=inner, outer=outer, t=t)


def _blend(flat: Tensor, t: Tensor, inner: Tensor, outer: Tensor) -> Tensor:
    """``antialias``'s blend of (pixels, C) rows across the pairs. Pure tensor code: compiled on CUDA."""
    t = t.to(flat.dtype)
    w_in = torch.relu(0.5 - t)
    w_out = torch.relu(t - 0.5)
    inner_v, outer_v = gather_rows(flat, inner), gather_rows(flat, outer)
    pull = torch.zeros_like(flat).index_add(0, inner, w_in.unsqueeze(-1) * (outer_v - inner_v))
    pull = pull.index_add(0, outer, w_out.unsqueeze(-1) * (inner_v - outer_v))
    weight = flat.new_zeros(flat.shape[0]).index_add(0, inner, w_in).index_add(0, outer, w_out)
    return flat + pull / weight.clamp(min=1.0).unsqueeze(-1)


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
    out = compiled_for(_blend, flat.device)(flat, crossings.t, crossings.inner, crossings.outer)
    return out.reshape(image.shape)
