"""Differentiable triangle rasteriser in pure PyTorch, batched over views, with edge-based anti-aliasing.

Three passes, the first one free of autograd:

1. **Visibility** (``rasterize``). Every drawable triangle of every view is expanded into the pixels
   of its screen bounding box; pixel centres are tested against the three edge functions and the
   survivors write ``quantised NDC depth · 2^id_bits + face_id`` into a flat ``(B·H·W)`` int64
   z-buffer with ``scatter_reduce(amin)``: nearest depth wins, ties go to the lower face id. The
   (triangle, pixel) pairs are generated in slices of at most ``RasterConfig.max_pairs_per_chunk``
   (a running-count ``searchsorted`` maps each pair to its triangle), so memory stays bounded however
   many faces or views there are.
   Clipping: a triangle with any vertex at ``w <= near_w`` (behind the camera or crossing the
   camera plane) is culled whole rather than clipped; fragments outside NDC depth [-1, 1] (in front of
   the near plane or beyond the far plane) are discarded per pixel. Zero-area triangles and
   non-finite vertices are never drawn; back faces are drawn unless ``cull_backfaces``.

2. **Barycentrics** (differentiable). For each covered pixel the winning triangle's screen-space
   barycentrics are recomputed from the clip vertices and made perspective-correct,
   ``β_k = (λ_k/w_k) / Σ_j λ_j/w_j``; the view depth ``w`` is ``1 / Σ_j λ_j/w_j``. ``interpolate``
   uses β, so attribute losses give gradients to the vertices inside the silhouette.

3. **Silhouette anti-aliasing** (``silhouette_crossings`` + ``antialias``): in
   ``morpheus_core.render.antialias``, which describes the method and why its gradient is right.

Conventions: clip space is OpenGL's (NDC x right, y up, z in [-1, 1], w = −z_camera); image row 0
is the top; pixel (i, j) has its centre at NDC ``x = (2j+1)/W − 1``, ``y = 1 − (2i+1)/H``. Internally
we use pixel coordinates ``sx = (x+1)·W/2 − ½`` (column) and ``sy = (1−y)·H/2 − ½`` (row), in which
pixel centres are integers; a triangle that is counter-clockwise in NDC (front-facing) has negative
signed area there. Half-precision clip coordinates are rasterised in float32 (a 512-px image
already needs more than fp16's 11 significant bits to place an edge).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import cached_property

import torch
from torch import Tensor

from morpheus_core.geometry.mesh import MeshIndexError, MeshTopology, mesh_topology
from morpheus_core.runtime.devices import compiled_for
from morpheus_core.runtime.gather import gather_batched_rows, gather_rows

_INT64_MAX = torch.iinfo(torch.int64).max
# Bits of the packed z-buffer key spent on depth at most; the rest (below bit 62) hold the face id.
_MAX_DEPTH_BITS = 40
# A triangle whose |area| is below this many machine epsilons times its longest edge² is degenerate.
_DEGENERATE_REL = 64


@dataclass(frozen=True)
class RasterConfig:
    """Memory bounds and degeneracy tolerances of the rasteriser (and of its silhouette anti-aliasing).

    ``max_pairs_per_chunk``: a 300k-face sphere at 512², batch 4, makes ~3.5M pairs: two slices.
    ``min_area_px``: triangles below 64 machine epsilons times their longest edge² (collinear up to
    rounding) are skipped too."""

    max_pairs_per_chunk: int = 1 << 21
    """(Triangle, pixel) or (edge, pixel) pairs per slice; each costs ~150 B of temporaries: 2^21 caps ~300 MB."""
    cull_backfaces: bool = False
    """Skip back-facing triangles (by screen winding); false draws both sides."""
    near_w: float = 1e-5
    """Triangles with a vertex at clip w ≤ this (behind or crossing the camera plane) are culled whole."""
    min_area_px: float = 1e-10
    """Triangles with |screen area| below this (px²) count as degenerate and are skipped."""
    min_edge_px: float = 1e-6
    """Anti-aliasing: silhouette edges shorter than this (px) on screen give no crossing (slope undefined)."""

    def __post_init__(self) -> None:
        if self.max_pairs_per_chunk < 1:
            raise ValueError(f"max_pairs_per_chunk must be >= 1, got {self.max_pairs_per_chunk}")
        if self.near_w < 0 or self.min_area_px < 0 or self.min_edge_px < 0:
            raise ValueError("near_w, min_area_px and min_edge_px must be non-negative")


class RasterInputError(ValueError):
    """Bad shapes, dtypes or indices handed to the rasteriser."""


@dataclass
class Fragments:
    """What the rasteriser saw. Per covered pixel (sparse, N = number of covered pixels over all
    views): ``pixel_index`` (N,) flat index into B·H·W, ``face`` (N,) face id, ``bary`` (N, 3)
    perspective-correct barycentrics and ``view_depth`` (N,) camera-space depth w, both
    differentiable w.r.t. ``clip``. ``face_id`` (B, H, W) is the dense id map, -1 on background.
    ``orientation`` (B, F) int8: +1 front-facing, -1 back-facing, 0 not drawn."""

    clip: Tensor
    faces: Tensor
    height: int
    width: int
    face_id: Tensor
    pixel_index: Tensor
    face: Tensor
    bary: Tensor
    view_depth: Tensor
    orientation: Tensor
    config: RasterConfig = field(default_factory=RasterConfig)
    topology: MeshTopology | None = field(default=None, repr=False)
    """The faces' edges when the caller had them (``Mesh.topology``); else built by ``edges``."""

    @property
    def batch(self) -> int:
        return int(self.face_id.shape[0])

    @property
    def mask(self) -> Tensor:
        """(B, H, W, 1) hard coverage as 0/1 in the clip dtype."""
        return (self.face_id >= 0).unsqueeze(-1).to(self.bary.dtype)

    def scatter(self, values: Tensor, fill: float = 0.0) -> Tensor:
        """Dense (B, H, W, C) image from per-covered-pixel values (N, C); ``fill`` elsewhere."""
        flat = values.new_full((self.batch * self.height * self.width, values.shape[-1]), fill)
        flat = flat.index_put((self.pixel_index,), values)
        return flat.reshape(self.batch, self.height, self.width, values.shape[-1])

    @property
    def depth(self) -> Tensor:
        """(B, H, W) view depth w (distance along the camera axis), 0 on background."""
        return self.scatter(self.view_depth.unsqueeze(-1))[..., 0]

    @cached_property
    def edges(self) -> MeshTopology:
        """The faces' unique edges and their adjacent faces, for the silhouette anti-aliasing."""
        if self.topology is not None:
            return self.topology
        try:
            return mesh_topology(self.faces, self.clip.shape[1])
        except MeshIndexError as err:  # unreachable after _check_inputs; kept typed
            raise RasterInputError(str(err)) from err


def _check_inputs(clip: Tensor, faces: Tensor, height: int, width: int, checked: MeshTopology | None) -> Tensor:
    """Shapes, dtypes, devices and the face index range; the range costs a host read unless ``checked``
    (a mesh's topology, checked against the same vertex count when it was built)."""
    if clip.dim() == 2:
        clip = clip.unsqueeze(0)
    if clip.dim() != 3 or clip.shape[-1] != 4:
        raise RasterInputError(f"clip vertices must be (B, V, 4) or (V, 4), got {tuple(clip.shape)}")
    if not clip.is_floating_point():
        raise RasterInputError(f"clip vertices must be floating point, got {clip.dtype}")
    if faces.dim() != 2 or faces.shape[-1] != 3:
        raise RasterInputError(f"faces must be (F, 3), got {tuple(faces.shape)}")
    if faces.dtype != torch.int64:
        raise RasterInputError(f"faces must be int64, got {faces.dtype}")
    if faces.device != clip.device:
        raise RasterInputError(f"faces on {faces.device} but clip vertices on {clip.device}")
    if checked is not None:
        if checked.num_vertices != clip.shape[1]:
            raise RasterInputError(f"the faces' topology was built for {checked.num_vertices} vertices, "
                                   f"the clip vertices have {clip.shape[1]}")
        if not checked.is_current():
            raise RasterInputError("the faces were changed in place after their topology was built: "
                                   "build a new Mesh (or call mesh_topology again)")
    elif faces.numel():
        lowest, highest = torch.stack(torch.aminmax(faces)).tolist()  # one host read
        if lowest < 0 or highest >= clip.shape[1]:
            raise RasterInputError(f"face indices must lie in [0, {clip.shape[1]}), got [{lowest}, {highest}]")
    if height < 1 or width < 1:
        raise RasterInputError(f"image size must be positive, got {height}x{width}")
    if clip.dtype in (torch.float16, torch.bfloat16):
        clip = clip.float()
    return clip


def clip_to_pixels(clip: Tensor, height: int, width: int, near_w: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Pixel coordinates (sx, sy), NDC depth and a per-vertex 'in front of the camera' flag.

    Vertices at w <= near_w are divided by 1 instead, so nothing non-finite is produced; every
    triangle using them is culled by the caller."""
    w = clip[..., 3]
    ok = (w > near_w) & torch.isfinite(clip).all(-1)
    w_safe = torch.where(ok, w, torch.ones_like(w))
    x = torch.where(ok, clip[..., 0], torch.zeros_like(w)) / w_safe
    y = torch.where(ok, clip[..., 1], torch.zeros_like(w)) / w_safe
    z = torch.where(ok, clip[..., 2], torch.zeros_like(w)) / w_safe
    sx = (x + 1.0) * (0.5 * width) - 0.5
    sy = (1.0 - y) * (0.5 * height) - 0.5
    return sx, sy, z, ok


def _signed_area(x: Tensor, y: Tensor) -> Tensor:
    """Twice the signed area of triangles with corner coordinates x, y (..., 3)."""
    x0, x1, x2 = x.unbind(-1)
    y0, y1, y2 = y.unbind(-1)
    return (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0)


def _edge_functions(x: Tensor, y: Tensor, px: Tensor, py: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Edge functions e_k of the edge opposite corner k at points (px, py); e_k / area are the
    screen-space barycentrics.

    Written relative to an edge end point (not as a·px + b·py + c) so that small triangles far from
    the origin keep their precision in float32; spelled out per corner because ``roll`` / fancy
    indexing of the (N, 3) corner tensors costs more than the arithmetic."""
    x0, x1, x2 = x.unbind(-1)
    y0, y1, y2 = y.unbind(-1)
    e0 = (x2 - x1) * (py - y1) - (y2 - y1) * (px - x1)
    e1 = (x0 - x2) * (py - y2) - (y0 - y2) * (px - x2)
    e2 = (x1 - x0) * (py - y0) - (y1 - y0) * (px - x0)
    return e0, e1, e2


def pair_chunks(counts: Tensor, chunk: int) -> Iterator[tuple[Tensor, Tensor]]:
    """All pairs (owner, k) with 0 <= k < counts[owner], in slices of at most ``chunk`` pairs; one
    host read (the total). The first end past a pair's index is its owner's, so owners without
    pairs are skipped without being listed first."""
    if counts.numel() == 0:
        return
    ends = torch.cumsum(counts, 0)
    total = int(ends[-1])
    for start in range(0, total, chunk):
        idx = torch.arange(start, min(start + chunk, total), device=counts.device)
        owner = torch.searchsorted(ends, idx, right=True)
        yield owner, idx - (ends[owner] - counts[owner])


def pixel_span(lo: Tensor, hi: Tensor, size: int) -> tuple[Tensor, Tensor]:
    """Integer pixel-centre range [first, last] inside [lo, hi] ∩ [0, size-1]; empty when last < first."""
    first = torch.ceil(lo.clamp(-1.0, float(size))).long().clamp(min=0)
    last = torch.floor(hi.clamp(-1.0, float(size))).long().clamp(max=size - 1)
    return first, last


def _triangle_setup(clip: Tensor, faces: Tensor, height: int, width: int, near_w: float, min_area_px: float,
                    cull_backfaces: bool) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Per view and triangle: orientation (B, F) int8, pixel-pair count (B·F,) of its screen box (0
    when not drawn), packed corners (B·F, 10: x, y, NDC depth, area) and box (B·F, 3: first column,
    first row, width). Pure tensor code: compiled on CUDA (``compiled_for``)."""
    sx, sy, z, ok = clip_to_pixels(clip, height, width, near_w)
    tx, ty, tz = sx[:, faces], sy[:, faces], z[:, faces]  # (B, F, 3)
    area = _signed_area(tx, ty)
    # Degenerate: tiny area in pixels, or tiny relative to the longest edge (collinear corners
    # whose area is only rounding noise — that noise grows with the coordinates' magnitude).
    longest = ((tx - tx.roll(-1, -1)) ** 2 + (ty - ty.roll(-1, -1)) ** 2).amax(-1)
    eps = _DEGENERATE_REL * torch.finfo(tx.dtype).eps
    drawable = ok[:, faces].all(-1) & (area.abs() > torch.clamp(eps * longest, min=min_area_px))
    front = area < 0
    if cull_backfaces:
        drawable &= front
    orientation = torch.where(drawable, torch.where(front, 1, -1), 0).to(torch.int8)
    j0, j1 = pixel_span(tx.amin(-1), tx.amax(-1), width)
    i0, i1 = pixel_span(ty.amin(-1), ty.amax(-1), height)
    box_w = (j1 - j0 + 1).clamp(min=0)
    counts = (box_w * (i1 - i0 + 1).clamp(min=0) * drawable).reshape(-1)
    # One gather per pair instead of several: corners, depths and area packed in one row.
    corners = torch.cat([tx, ty, tz, area.unsqueeze(-1)], -1).reshape(-1, 10)
    boxes = torch.stack([j0, i0, box_w], -1).reshape(-1, 3)
    return orientation, counts, corners, boxes


def _pair_keys(tri: Tensor, local: Tensor, boxes: Tensor, corners: Tensor, num_faces: int, width: int, hw: int,
               id_scale: int, depth_scale: float) -> tuple[Tensor, Tensor]:
    """Flat pixel (P,) and packed z-buffer key (P,) of (triangle, k-th pixel of its box) pairs; pairs
    outside the triangle or the depth range get the neutral key. Every pair writes one: a masked
    index would be a host sync. Pure tensor code: compiled on CUDA. ``id_scale`` = 2^id_bits (a
    product, not a shift: dynamo in torch 2.11 cannot shift by a symbolic int)."""
    box = boxes[tri]
    px = box[:, 0] + local % box[:, 2]
    py = box[:, 1] + local // box[:, 2]
    c = corners[tri]
    e0, e1, e2 = _edge_functions(c[:, 0:3], c[:, 3:6], px.to(c.dtype), py.to(c.dtype))
    a = c[:, 9]
    inside = (e0 * a >= 0) & (e1 * a >= 0) & (e2 * a >= 0)
    depth = (e0 * c[:, 6] + e1 * c[:, 7] + e2 * c[:, 8]) / a
    inside &= (depth >= -1.0) & (depth <= 1.0)
    quant = ((depth.clamp(-1.0, 1.0) + 1.0) * (0.5 * depth_scale)).long()
    key = quant * id_scale + tri % num_faces
    pixel = (tri // num_faces) * hw + py * width + px
    return pixel, torch.where(inside, key, _INT64_MAX)


def rasterize(clip: Tensor, faces: Tensor | MeshTopology, height: int, width: int,
              config: RasterConfig | None = None) -> Fragments:
    """Rasterise triangles ``faces`` (F, 3) int64 over clip-space vertices ``clip`` (B, V, 4) or (V, 4)
    into ``height`` × ``width`` images per view; see the module docstring for the rules. ``faces`` may be
    a mesh's ``topology``: its index check and edges are then reused, not redone (two host reads and
    an edge sort per call, which a launch-bound stage pays every step)."""
    config = config or RasterConfig()
    topology = faces if isinstance(faces, MeshTopology) else None
    faces = topology.faces if topology is not None else faces
    clip = _check_inputs(clip, faces, height, width, topology)
    batch, num_faces, device = clip.shape[0], faces.shape[0], clip.device
    hw = height * width

    with torch.no_grad():
        orientation, counts, corners, boxes = compiled_for(_triangle_setup, device)(
            clip.detach(), faces, height, width, config.near_w, config.min_area_px, config.cull_backfaces)
        id_bits = max(1, num_faces.bit_length())
        id_scale = 1 << id_bits
        depth_scale = float((1 << min(_MAX_DEPTH_BITS, 62 - id_bits)) - 1)
        zbuf = torch.full((batch * hw,), _INT64_MAX, dtype=torch.int64, device=device)
        for tri, local in pair_chunks(counts, config.max_pairs_per_chunk):
            pixel, key = compiled_for(_pair_keys, device)(tri, local, boxes, corners, max(num_faces, 1), width, hw,
                                                          id_scale, depth_scale)
            zbuf.scatter_reduce_(0, pixel, key, reduce="amin", include_self=True)

        covered = zbuf != _INT64_MAX
        face_flat = torch.where(covered, zbuf % id_scale, -1)  # covered keys are ≥ 0
        pixel_index = covered.nonzero().squeeze(1)
        face = face_flat[pixel_index]

    bary, view_depth = compiled_for(_perspective_barycentrics, device)(clip, faces, pixel_index, face, height, width)
    return Fragments(clip=clip, faces=faces, height=height, width=width,
                     face_id=face_flat.reshape(batch, height, width), pixel_index=pixel_index, face=face,
                     bary=bary, view_depth=view_depth, orientation=orientation, config=config,
                     topology=topology)


def _perspective_barycentrics(clip: Tensor, faces: Tensor, pixel_index: Tensor, face: Tensor,
                              height: int, width: int) -> tuple[Tensor, Tensor]:
    """Differentiable perspective-correct barycentrics (N, 3) and view depth (N,) at covered pixels.

    Only winning triangles get here, so every w is > near_w and every area is non-zero."""
    hw = height * width
    view = pixel_index // hw
    py = (pixel_index % hw) // width
    px = pixel_index % width
    corners = gather_batched_rows(clip, view.unsqueeze(-1), faces[face])  # (N, 3, 4)
    w = corners[..., 3]
    sx = (corners[..., 0] / w + 1.0) * (0.5 * width) - 0.5
    sy = (1.0 - corners[..., 1] / w) * (0.5 * height) - 0.5
    e = torch.stack(_edge_functions(sx, sy, px.to(clip.dtype), py.to(clip.dtype)), -1)
    over_w = (e / _signed_area(sx, sy).unsqueeze(-1)) / w
    total = over_w.sum(-1, keepdim=True)
    return over_w / total, 1.0 / total.squeeze(-1)


def interpolate(attributes: Tensor, fragments: Fragments) -> Tensor:
    """Per-vertex ``attributes`` (V, C) or (B, V, C) interpolated at covered pixels → (B, H, W, C),
    zero on background. Differentiable w.r.t. the attributes and (through β) the clip vertices."""
    return fragments.scatter(interpolate_sparse(attributes, fragments))


def interpolate_sparse(attributes: Tensor, fragments: Fragments) -> Tensor:
    """Like ``interpolate`` but only the covered pixels: (N, C) in ``fragments.pixel_index`` order."""
    if attributes.dim() not in (2, 3) or attributes.shape[-2] != fragments.clip.shape[1]:
        raise RasterInputError(f"attributes must be (V, C) or (B, V, C) with V = {fragments.clip.shape[1]}, "
                               f"got {tuple(attributes.shape)}")
    corner_ids = fragments.faces[fragments.face]  # (N, 3)
    if attributes.dim() == 2:
        corners = gather_rows(attributes, corner_ids)
    else:
        if attributes.shape[0] not in (1, fragments.batch):
            raise RasterInputError(f"attribute batch {attributes.shape[0]} does not match {fragments.batch} views")
        view = fragments.pixel_index // (fragments.height * fragments.width)
        view = view if attributes.shape[0] > 1 else torch.zeros_like(view)
        corners = gather_batched_rows(attributes, view.unsqueeze(-1), corner_ids)
    return (fragments.bary.to(corners.dtype).unsqueeze(-1) * corners).sum(-2)
