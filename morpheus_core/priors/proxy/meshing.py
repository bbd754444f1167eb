"""Meshing of the inflated proxy (``priors.proxy.shape.InflatedProxy``, read through ``Silhouette``): its SDF
on a closed DMTet grid.

Marching tetrahedra on a DMTet grid with a closed boundary, so a frame-filling silhouette (cut by
the image border) is capped at the grid and the mesh stays closed. Silhouette components too thin
to hold a grid vertex are seeded with one first (``_seed_components_between_vertices``), so specks
and thin parts keep a surface.
"""

from __future__ import annotations

import math
import warnings
from typing import Protocol

import cv2
import numpy as np
import torch
from torch import Tensor

from morpheus_core.cameras import OrbitConfig
from morpheus_core.geometry.mesh import Mesh
from morpheus_core.geometry.tet_surface import DMTet, DMTetConfig
from morpheus_core.geometry.tets import EDGE_OFFSETS

# Grid vertices per SDF call: the grid-128 pipeline setting has 2.1M vertices, whose bilinear
# lookups would otherwise allocate several (N, …) temporaries at once.
_SDF_CHUNK = 1 << 18
# A rescued vertex is moved at most this fraction of DMTet's deformation range (tanh never
# reaches 1, and staying below it keeps the moved vertex's tets from flattening).
_MAX_SNAP = 0.99
# A component counts as meshed only if some grid vertex lies this many cells deep inside it.
_SHALLOW_CELLS = 0.25
# The 7 positive lattice steps along the tet grid's edges (their negatives are the other 7).
_EDGE_STEPS = torch.from_numpy(EDGE_OFFSETS)


def _non_manifold_edges(mesh: Mesh) -> tuple[int, int]:
    """(edges not used by exactly two faces, all edges), in numpy: torch.unique on CPU took ~0.2 s for
    30k keys on the 2-core machine, longer than the rest of the mesh build."""
    faces = mesh.faces.cpu().numpy()
    a, b = faces, np.roll(faces, -1, axis=1)
    keys = (np.minimum(a, b) * mesh.num_vertices + np.maximum(a, b)).ravel()
    _, counts = np.unique(keys, return_counts=True)
    return int((counts != 2).sum()), int(counts.size)


class Silhouette(Protocol):
    """What meshing reads of an inflated silhouette (``priors.proxy.shape.InflatedProxy`` is one)."""

    device: torch.device
    height: int
    width: int
    orbit: OrbitConfig
    touches_border: bool
    mask_array: np.ndarray
    distance_px: np.ndarray

    def sdf(self, points: Tensor) -> Tensor: ...

    def pixel_coordinates(self, points: Tensor) -> Tensor: ...


def build_mesh(proxy: Silhouette, grid_resolution: int, half_extent: float) -> Mesh:
    """The proxy's closed surface: its SDF meshed by marching tets on a closed DMTet grid of ``grid_resolution``
    cells per side spanning ±``half_extent``."""
    dmtet = DMTet(DMTetConfig(resolution=grid_resolution, half_extent=half_extent, close_boundary=True),
                  device=proxy.device)
    grid = dmtet.grid_vertices
    values = torch.cat([proxy.sdf(grid[i:i + _SDF_CHUNK]) for i in range(0, grid.shape[0], _SDF_CHUNK)])
    if not bool(torch.isfinite(values).all()):
        raise RuntimeError("the proxy SDF is not finite on the grid (a bug: D and Dmax are finite)")
    capped = int((values[dmtet.boundary] < 0).sum())
    if capped and not proxy.touches_border:
        warnings.warn(f"the inflated proxy reaches the grid boundary at {capped} vertices and is capped flat at "
                      f"±{half_extent}; lower thickness or raise half_extent to keep its full depth",
                      RuntimeWarning, stacklevel=3)
    # DMTet caps these anyway (close_boundary); doing it here also keeps a sign change when
    # the shape fills the whole grid.
    values = torch.where(dmtet.boundary, values.clamp_min(0.0), values)
    deform = torch.zeros_like(grid)
    _seed_components_between_vertices(proxy, dmtet, values, deform)
    # Not init_from_sdf: it resets the deformation the seeding uses, and refuses a grid with
    # no inside vertex, which is exactly what a silhouette smaller than a cell gives.
    dmtet.sdf.copy_(values)
    dmtet.deform.copy_(deform)
    mesh = dmtet.extract()
    mesh = Mesh(mesh.vertices.detach(), mesh.faces.detach())
    bad, total = _non_manifold_edges(mesh)
    if bad:
        warnings.warn(f"the proxy mesh is not watertight: {bad} of {total} edges are not shared by exactly two "
                      "faces (the SDF is exactly zero on grid vertices)", RuntimeWarning, stacklevel=3)
    return mesh


def _seed_components_between_vertices(proxy: Silhouette, dmtet: DMTet, values: Tensor, deform: Tensor) -> None:
    """Give every silhouette component that holds no inside grid vertex one, in place.

    A blob thinner than a grid cell can fall between the vertices and vanish from the mesh (or
    leave no surface at all). For each such component the grid vertex nearest to its deepest
    point (on z = 0) is moved there through DMTet's deformation — at most half a cell per
    axis, which the nearest vertex never needs more than — and given the SDF there, so
    marching tets wraps a small closed blob around it. Its 14 grid neighbours move along
    with it, so the tets around it keep their shape and the blob is centred and round (moved
    alone, the vertex would sit at the flat edge of a lopsided star); when another solid is
    within two grid steps the vertex moves alone, leaving the neighbours' other tets intact.
    """
    n_labels, labels = cv2.connectedComponents(proxy.mask_array.astype(np.uint8), connectivity=8)
    grid, boundary = dmtet.grid_vertices, dmtet.boundary

    def label_of(points: Tensor) -> np.ndarray:
        uv = proxy.pixel_coordinates(points).floor().long().cpu().numpy()
        return labels[np.clip(uv[:, 1], 0, proxy.height - 1), np.clip(uv[:, 0], 0, proxy.width - 1)]

    # A vertex barely inside (a speck whose edge grazes it) gives a blob far smaller than the
    # speck, too small to show in a render: such a component counts as uncovered and is seeded.
    deep = (values < -_SHALLOW_CELLS * dmtet.config.cell_size) & ~boundary
    covered = np.zeros(n_labels, dtype=bool)
    if bool(deep.any()):
        covered[np.unique(label_of(grid[deep]))] = True
    covered[0] = True  # background
    if covered.all():
        return

    # Where to seed each component: the mean of its pixels within a hair of its maximal D, so a
    # symmetric speck whose maximum is a tie of 2–4 pixels is seeded at its true centre; one
    # of those pixels when the mean falls outside (a non-convex component with tied maxima).
    dist = proxy.distance_px.astype(np.float64)
    peak = np.full(n_labels, -np.inf)
    np.maximum.at(peak, labels.ravel(), dist.ravel())
    top = (dist >= peak[labels] - 1e-3) & (labels > 0)
    rows, cols = np.nonzero(top)
    top_labels = labels[top]
    count = np.bincount(top_labels, minlength=n_labels).clip(min=1)
    mean_uv = np.stack([np.bincount(top_labels, weights=cols + 0.5, minlength=n_labels) / count,
                        np.bincount(top_labels, weights=rows + 0.5, minlength=n_labels) / count], -1)
    one_uv = np.zeros((n_labels, 2))
    _, first = np.unique(top_labels, return_index=True)
    one_uv[top_labels[first]] = np.stack([cols[first] + 0.5, rows[first] + 0.5], -1)

    res, h = dmtet.config.resolution, dmtet.config.half_extent
    cell, step = dmtet.config.cell_size, dmtet.config.deform_scale * dmtet.config.cell_size
    half_span = proxy.orbit.distance * math.tan(math.radians(proxy.orbit.fov_deg) / 2)  # z = 0 plane
    star = torch.cat([torch.zeros(1, 3, dtype=torch.int64), _EDGE_STEPS, -_EDGE_STEPS]).to(grid.device)
    ring2 = (star[:, None] + star[None]).reshape(-1, 3)
    moved = torch.zeros_like(boundary)

    def index(ijk: Tensor) -> Tensor:
        ijk = ijk.clamp(0, res)
        return (ijk[..., 0] * (res + 1) + ijk[..., 1]) * (res + 1) + ijk[..., 2]

    for label in np.flatnonzero(~covered):
        for u, v in (mean_uv[label], one_uv[label]):
            target = torch.tensor([(2 * u / proxy.width - 1) * half_span * proxy.width / proxy.height,
                                   (1 - 2 * v / proxy.height) * half_span, 0.0], dtype=grid.dtype,
                                  device=grid.device)
            ijk = torch.round((target + h) / cell).long()
            if bool((ijk <= 0).any() or (ijk >= res).any()):
                continue  # on or beyond the capped boundary: nothing can be inside there
            centre = index(ijk)
            if not bool(proxy.sdf(target[None])[0] < 0):
                continue  # no depth here
            if bool(values[centre] < 0) and label_of(grid[centre][None])[0] != label:
                continue  # inside another solid: moving it would dent that
            members = index(ijk + star)
            if bool((values[index(ijk + ring2)] < 0).any() or moved[members].any()):
                members = centre[None]
            offset = torch.atanh(((target - grid[centre]) / step).clamp(-_MAX_SNAP, _MAX_SNAP))
            deform[members] = offset
            moved[members] = True
            new = proxy.sdf(grid[members] + step * torch.tanh(offset))
            values[members] = torch.where(boundary[members], new.clamp_min(0.0), new)
            break
