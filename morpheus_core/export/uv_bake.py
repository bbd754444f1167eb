"""UV baking: from an optimised mesh + colour field to an unwrapped mesh with a texture image.

* ``bake_uv``: xatlas cuts and packs the mesh into charts; the UV triangles are rasterised in UV
  space with the same rasteriser (orthographic: clip = (2u − 1, 2v − 1, 0, 1)); every covered texel
  gets the 3-D surface position interpolated from its triangle, and the field's colour there. Empty
  texels around the charts are then filled by seam dilation (repeated 3×3 averages of filled
  neighbours), so bilinear lookups near a chart border never pull in background.
* Image orientation: the rasteriser's row 0 is the top of the image, i.e. NDC y = +1, i.e. v = 1.
  So the baked image has **row 0 at v = 1** — the OBJ / trimesh convention — and is handed to trimesh
  unflipped (``morpheus_core.export.gltf``); trimesh writes glTF's top-left UV origin (v ↦ 1 − v)
  itself. (An image laid out with row 0 at v = 0 would need a vertical flip first.)
  ``tests/test_texture.py`` checks both the trimesh round trip and the raw glTF texture coordinates
  against the baked colours.
* Size limit: xatlas's cost grows faster than linearly (≈45 s at 109k faces on two cores), so meshes
  above ``BakeConfig.max_faces`` are decimated by vertex clustering (with a warning) or rejected
  with ``TooManyFacesError``; either message names the DMTet grid resolution that fits the budget
  (``morpheus_core.geometry.tet_surface.suggest_resolution``).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F
import xatlas
from torch import Tensor

from morpheus_core.geometry.mesh import Mesh
from morpheus_core.geometry.tet_surface import suggest_resolution
from morpheus_core.geometry.textured_mesh import BakedTexture
from morpheus_core.render.raster import RasterConfig, interpolate_sparse, rasterize

ColourField = Callable[[Tensor], Tensor]


class TooManyFacesError(ValueError):
    """The mesh exceeds the export face budget and the configuration says not to decimate."""


class EmptyMeshError(ValueError):
    """There is nothing to unwrap: the mesh has no faces."""


@dataclass(frozen=True)
class BakeConfig:
    """UV unwrapping (xatlas) and baking of a colour field into a square texture."""

    texture_size: int = 1024
    """Side (texels) of the baked square texture (the paper: 1024)."""
    padding: int = 4
    """Gap between charts in xatlas atlas texels; keep ≥ 2: the texture may be ~1.3× coarser than xatlas's atlas."""
    dilation_iterations: int = 8
    """Texels the chart colours are pushed outward into empty texels (keep ≥ padding): no background at seams."""
    max_faces: int = 50_000
    """Export face budget: xatlas's cost grows faster than linearly (≈ 45 s at 109k faces on two cores)."""
    on_too_many_faces: Literal["decimate", "raise"] = "decimate"
    """Above ``max_faces``: ``decimate`` by vertex clustering (with a warning) or ``raise`` TooManyFacesError."""
    query_chunk: int = 1 << 18
    """Texel points per colour-field call: bounds peak memory, not the result."""
    raster: RasterConfig = field(default_factory=RasterConfig)

    def __post_init__(self) -> None:
        if self.texture_size < 8:
            raise ValueError(f"texture_size must be ≥ 8, got {self.texture_size}")
        if self.padding < 0 or self.dilation_iterations < 0:
            raise ValueError("padding and dilation_iterations must be non-negative")
        if self.max_faces < 4:
            raise ValueError(f"max_faces must be ≥ 4, got {self.max_faces}")
        if self.on_too_many_faces not in ("decimate", "raise"):
            raise ValueError(f"on_too_many_faces must be 'decimate' or 'raise', got {self.on_too_many_faces!r}")


def _surface_area(mesh: Mesh) -> float:
    return float(mesh.face_normals(normalize=False).detach().norm(dim=-1).sum() / 2)


def cluster_decimate(mesh: Mesh, max_faces: int) -> Mesh:
    """Vertex-clustering decimation to at most ``max_faces`` faces, without extra dependencies.

    Vertices are snapped to a cubic grid and merged per cell (at their mean), collapsed and
    duplicate faces are dropped; the finest grid that meets the budget is found by bisection.
    Coarse (surface error up to one cell) but robust on any triangle soup."""
    verts = mesh.vertices.detach().double().cpu().numpy()
    faces = mesh.faces.cpu().numpy()
    lo = verts.min(0)
    extent = float((verts.max(0) - lo).max()) or 1.0

    def cluster(cells: int) -> tuple[np.ndarray, np.ndarray]:
        key = np.minimum(np.floor((verts - lo) / extent * cells), cells - 1).astype(np.int64)
        flat = (key[:, 0] * cells + key[:, 1]) * cells + key[:, 2]
        _, inverse = np.unique(flat, return_inverse=True)
        counts = np.bincount(inverse)
        new_v = np.stack([np.bincount(inverse, verts[:, k]) for k in range(3)], 1) / counts[:, None]
        f = inverse[faces]
        f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])]
        _, first = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
        f = f[np.sort(first)]
        used, f = np.unique(f, return_inverse=True)
        return new_v[used], f.reshape(-1, 3)

    lo_cells, hi_cells = 1, 4096
    best = cluster(lo_cells)
    while hi_cells - lo_cells > 1:
        mid = (lo_cells + hi_cells) // 2
        candidate = cluster(mid)
        if len(candidate[1]) <= max_faces:
            lo_cells, best = mid, candidate
        else:
            hi_cells = mid
    v, f = best
    faces_out = torch.from_numpy(f).to(device=mesh.faces.device, dtype=torch.int64)
    return Mesh(torch.from_numpy(v).to(mesh.vertices), faces_out)


def _enforce_face_limit(mesh: Mesh, config: BakeConfig) -> Mesh:
    if mesh.num_faces <= config.max_faces:
        return mesh
    res = suggest_resolution(config.max_faces, surface_area=_surface_area(mesh))
    advice = (f"mesh has {mesh.num_faces} faces, over the export budget of {config.max_faces} (xatlas time grows "
              f"faster than linearly); extract it with a DMTet grid resolution of about {res} or lower "
              f"(morpheus_core.geometry.tet_surface.suggest_resolution)")
    if config.on_too_many_faces == "raise":
        raise TooManyFacesError(advice)
    warnings.warn(advice + "; decimating by vertex clustering", stacklevel=3)
    return cluster_decimate(mesh, config.max_faces)


def _unwrap(vertices: np.ndarray, faces: np.ndarray, config: BakeConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    atlas = xatlas.Atlas()
    atlas.add_mesh(vertices.astype(np.float32), faces.astype(np.uint32))
    pack = xatlas.PackOptions()
    pack.resolution = config.texture_size
    pack.padding = config.padding
    pack.bilinear = True
    atlas.generate(pack_options=pack)
    if atlas.atlas_count != 1:
        raise RuntimeError(f"xatlas packed the charts into {atlas.atlas_count} atlases; expected one")
    vmapping, indices, uvs = atlas.get_mesh(0)
    # xatlas normalises by its own (w, h), which may differ a little from the requested square; the
    # square texture rescales them, keeping every chart and its padding (slightly scaled) in place.
    return vmapping.astype(np.int64), indices.astype(np.int64), uvs.astype(np.float32)


def dilate(image: Tensor, mask: Tensor, iterations: int) -> tuple[Tensor, Tensor]:
    """Push colours of ``image`` (H, W, C) outward from texels where ``mask`` (H, W) is set: each
    iteration fills every empty texel that has filled 3×3 neighbours with their mean. Returns the
    image and the grown mask; texels still empty afterwards get the mean colour of the filled ones
    (so no texel is left at an arbitrary value)."""
    img = image.permute(2, 0, 1).unsqueeze(0)
    m = mask.to(img.dtype)[None, None]
    for _ in range(iterations):
        total = F.avg_pool2d(img * m, 3, stride=1, padding=1)
        weight = F.avg_pool2d(m, 3, stride=1, padding=1)
        fill = (m == 0) & (weight > 0)
        img = torch.where(fill, total / weight.clamp(min=1e-12), img)
        m = torch.where(fill, torch.ones_like(m), m)
    out = img[0].permute(1, 2, 0)
    grown = m[0, 0] > 0
    if grown.any() and not grown.all():
        out = torch.where(grown.unsqueeze(-1), out, out[grown].mean(0))
    return out, grown


def bake_uv(mesh: Mesh, field: ColourField, config: BakeConfig | None = None) -> BakedTexture:
    """Unwrap ``mesh`` with xatlas and bake ``field`` (points (N, 3) → colours (N, 3) in [0, 1]) into a
    ``config.texture_size``² texture. The rasterisation and field queries run on the mesh's device."""
    config = config or BakeConfig()
    if mesh.num_faces == 0:
        raise EmptyMeshError("cannot bake a texture for a mesh without faces")
    source_faces = mesh.num_faces
    normals_source = mesh.vertex_normals().detach()
    mesh = _enforce_face_limit(mesh, config)
    if mesh.num_faces != source_faces:
        normals_source = mesh.vertex_normals().detach()
    device, size = mesh.vertices.device, config.texture_size
    vmapping, faces, uvs = _unwrap(mesh.vertices.detach().cpu().numpy(), mesh.faces.cpu().numpy(), config)

    vmap_t = torch.from_numpy(vmapping).to(device)
    positions = mesh.vertices.detach()[vmap_t]
    uv_t = torch.from_numpy(uvs).to(device=device, dtype=positions.dtype)
    clip = torch.cat([uv_t * 2 - 1, torch.zeros_like(uv_t[:, :1]), torch.ones_like(uv_t[:, :1])], dim=-1)
    faces_t = torch.from_numpy(faces).to(device)
    with torch.no_grad():
        frags = rasterize(clip, faces_t, size, size, config.raster)
        points = interpolate_sparse(positions, frags)
        colours = torch.cat([field(chunk) for chunk in points.split(config.query_chunk)]) if len(points) else \
            points.new_zeros(0, 3)
        if colours.shape != points.shape:
            raise ValueError(f"field must map (N, 3) points to (N, 3) colours, got {tuple(colours.shape)}")
        image = frags.scatter(colours.to(positions.dtype))[0]
        covered = frags.face_id[0] >= 0
        image, _ = dilate(image, covered, config.dilation_iterations)
        texture = (image.clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()
    return BakedTexture(
        vertices=positions.cpu().numpy().astype(np.float32), faces=faces, uvs=uvs,
        normals=normals_source[vmap_t].cpu().numpy().astype(np.float32), texture=texture,
        coverage=float(covered.float().mean()), source_faces=source_faces,
    )
