"""Marching tetrahedra: the zero level of a signed distance on a tet mesh, as a triangle ``Mesh``.

The extraction behind DMTet (``morpheus_core.geometry.tet_surface``); the tet grid is ``geometry.tets``.

Sign convention: **negative inside**, as for an ordinary signed distance (|x| − r for a sphere).
Tie rule: a value exactly 0 counts as *outside*. A surface vertex is placed on every grid edge
whose endpoints differ in sign, at the zero of the linear interpolant; where the outside endpoint
is exactly 0 that zero *is* the endpoint, and all crossings that land on the same grid vertex are
welded into one mesh vertex (triangles that collapse are dropped). So an SDF that vanishes on
grid vertices — a plane through a row of vertices, a shape touching the closed boundary — gives
a clean mesh with no zero-area triangles and no NaN. A welded vertex follows its grid vertex
(and its deformation) but not the SDF: moving it along one edge or another is a kink, not a
derivative. A grid vertex exactly at zero that joins two separate inside regions gives a
non-manifold vertex or edge; exact zeros of that kind do not survive a single optimiser step.

Faces are wound counter-clockwise seen from outside (right-hand normal points from the inside
corners of the tet to the outside ones), the convention of :class:`Mesh`.

The 16-case table is derived below from geometry rather than typed in: for every inside/outside
pattern of a positively oriented reference tet the crossing edges are collected (3 for one corner
against three, 4 forming a quad for two against two) and each triangle is flipped until its normal
points toward the outside corners. An orientation-preserving affine map takes the reference tet
to any positively oriented grid tet, so the winding holds for all of them.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from morpheus_core.geometry.mesh import Mesh
from morpheus_core.runtime.gather import gather_rows

# The six edges of a tet as corner pairs; "local edge e" below indexes this tuple.
TET_EDGES: tuple[tuple[int, int], ...] = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
_REFERENCE_TET = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


class EmptySurfaceError(ValueError):
    """The SDF has no sign change on the grid, so there is no surface to extract."""


class NonFiniteFieldError(ValueError):
    """The SDF, the deformation or the field it was initialised from holds NaN or ±inf."""


def _edge_id(a: int, b: int) -> int:
    return TET_EDGES.index((min(a, b), max(a, b)))


def _derive_table() -> tuple[np.ndarray, np.ndarray]:
    """(16, 2, 3) local edges of each case's triangles (−1 pads), and (16,) triangle counts.

    Case bit c is set when corner c is inside.
    """
    table = -np.ones((16, 2, 3), dtype=np.int64)
    counts = np.zeros(16, dtype=np.int64)
    mid = {e: _REFERENCE_TET[list(TET_EDGES[e])].mean(0) for e in range(6)}
    for case in range(16):
        inside = [c for c in range(4) if (case >> c) & 1]
        outside = [c for c in range(4) if not (case >> c) & 1]
        if len(inside) in (0, 4):
            continue
        if len(inside) == 2:
            (i0, i1), (o0, o1) = inside, outside
            # Consecutive quad corners share a tet corner, so this is the quad's boundary cycle.
            quad = [_edge_id(i0, o0), _edge_id(i0, o1), _edge_id(i1, o1), _edge_id(i1, o0)]
            tris = [[quad[0], quad[1], quad[2]], [quad[0], quad[2], quad[3]]]
        else:
            apex = inside[0] if len(inside) == 1 else outside[0]
            tris = [[_edge_id(apex, c) for c in range(4) if c != apex]]
        towards_outside = _REFERENCE_TET[outside].mean(0) - _REFERENCE_TET[inside].mean(0)
        for k, tri in enumerate(tris):
            p = [mid[e] for e in tri]
            if np.dot(np.cross(p[1] - p[0], p[2] - p[0]), towards_outside) < 0:
                tri = [tri[0], tri[2], tri[1]]
            table[case, k] = tri
        counts[case] = len(tris)
    return table, counts


TRIANGLE_TABLE, TRIANGLE_COUNT = _derive_table()
_TABLE_CACHE: dict[torch.device, tuple[Tensor, Tensor, Tensor, Tensor]] = {}


def _tables(device: torch.device) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    if device not in _TABLE_CACHE:
        edges = torch.tensor(TET_EDGES, dtype=torch.int64, device=device)
        _TABLE_CACHE[device] = (torch.from_numpy(TRIANGLE_TABLE).to(device),
                                torch.from_numpy(TRIANGLE_COUNT).to(device), edges[:, 0], edges[:, 1])
    return _TABLE_CACHE[device]


def _sign_change_error(what: str, inside: int, total: int) -> EmptySurfaceError | None:
    if inside == 0:
        return EmptySurfaceError(f"{what} is ≥ 0 at all {total} grid vertices: everything is outside, "
                                 "there is no surface (the shape vanished or was never initialised)")
    if inside == total:
        return EmptySurfaceError(f"{what} is < 0 at all {total} grid vertices: everything is inside, "
                                 "there is no surface (the shape fills the whole grid)")
    return None


def require_surface(finite: dict[str, Tensor], signed: dict[str, Tensor]) -> None:
    """Every ``finite`` tensor finite and every ``signed`` SDF with a sign change, read in one host sync.

    The checks run before each extraction, every step of the DMTet stage; one read instead of one
    per check keeps the host from waiting on the GPU several times a step. Raises
    NonFiniteFieldError or EmptySurfaceError naming the first tensor that fails, in dict order.
    """
    counts = torch.stack([(~torch.isfinite(t)).sum() for t in finite.values()]
                         + [(t < 0).sum() for t in signed.values()]).tolist()
    for name, bad in zip(finite, counts[:len(finite)], strict=True):
        if bad:
            raise NonFiniteFieldError(f"{name} has {int(bad)} non-finite value(s) (NaN or ±inf); the optimisation "
                                      "diverged or the field it came from is broken — lower the learning rate or "
                                      "restore the last checkpoint")
    for (what, sdf), inside in zip(signed.items(), counts[len(finite):], strict=True):
        error = _sign_change_error(what, int(inside), sdf.numel())
        if error is not None:
            raise error


def interpolate_crossing(pos_a: Tensor, pos_b: Tensor, sdf_a: Tensor, sdf_b: Tensor) -> Tensor:
    """The zero of the linear interpolant on segments a→b whose endpoints differ in sign.

    Values are divided by the larger magnitude per edge first, so 1e30 and 1e-30 scales give the
    same point without overflow. That divisor is detached: the crossing is homogeneous of degree
    0 in (sdf_a, sdf_b), so its derivative through the divisor is zero anyway.
    Rows with sdf_a == sdf_b == 0 (welded) return ``pos_a``.
    """
    scale = torch.maximum(sdf_a.abs(), sdf_b.abs()).detach()
    scale = torch.where(scale > 0, scale, torch.ones_like(scale))
    a, b = sdf_a / scale, sdf_b / scale
    denom = a - b
    denom = torch.where(denom != 0, denom, torch.ones_like(denom))
    t = (a / denom).unsqueeze(-1)
    return pos_a + t * (pos_b - pos_a)


def marching_tets(vertices: Tensor, tets: Tensor, sdf: Tensor) -> Mesh:
    """Triangle mesh of the zero level of ``sdf`` (negative inside) on a tet mesh.

    ``vertices`` (N, 3) float, ``tets`` (T, 4) int64 positively oriented, ``sdf`` (N,).
    Differentiable in ``vertices`` and ``sdf``. Crossing edges are deduplicated by the 1-D key
    i·N + j (i < j); crossings sitting on a grid vertex (the outside end is exactly 0) are keyed
    by that vertex instead, so they weld. Raises EmptySurfaceError without a sign change and
    NonFiniteFieldError on NaN/inf.
    """
    if vertices.dim() != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices must be (N, 3), got {tuple(vertices.shape)}")
    if tets.dim() != 2 or tets.shape[1] != 4 or tets.dtype != torch.int64:
        raise ValueError(f"tets must be (T, 4) int64, got {tuple(tets.shape)} {tets.dtype}")
    if sdf.shape != vertices.shape[:1]:
        raise ValueError(f"sdf must be ({vertices.shape[0]},), got {tuple(sdf.shape)}")
    require_surface({"sdf": sdf, "vertex positions": vertices}, {"SDF": sdf})
    return extract_surface(vertices, tets, sdf)


def extract_surface(vertices: Tensor, tets: Tensor, sdf: Tensor) -> Mesh:
    """:func:`marching_tets` without its input checks, for callers that ran :func:`require_surface`."""
    device, n = vertices.device, vertices.shape[0]
    table, count, edge_a, edge_b = _tables(device)

    # The case code of every tet from four uint8 gathers: a (T, 4) bool gather summed in int64
    # would move ~8× the bytes, and this pass over all T tets dominates the cost on a fine grid.
    inside = (sdf.detach() < 0).to(torch.uint8)
    code = inside[tets[:, 0]]
    for c in range(1, 4):
        code = code | (inside[tets[:, c]] << c)
    active = (code != 0) & (code != 15)
    tet_v = tets[active]
    case = code[active].long()
    corner_in = ((case[:, None] >> torch.arange(4, device=device)) & 1).bool()

    ends_a, ends_b = tet_v[:, edge_a], tet_v[:, edge_b]  # (Ta, 6): local edge endpoints
    crossing = corner_in[:, edge_a] != corner_in[:, edge_b]
    outside_end = torch.where(corner_in[:, edge_a], ends_b, ends_a)
    key = torch.minimum(ends_a, ends_b) * n + torch.maximum(ends_a, ends_b)
    on_vertex = sdf.detach()[outside_end] == 0
    key = torch.where(on_vertex, -1 - outside_end, key)  # a separate (negative) key space for welds
    unique_key, slot = torch.unique(key[crossing], return_inverse=True)

    welded = unique_key < 0
    weld_vertex = -1 - unique_key
    va = torch.where(welded, weld_vertex, torch.div(unique_key, n, rounding_mode="floor"))
    vb = torch.where(welded, weld_vertex, unique_key % n)
    points = interpolate_crossing(gather_rows(vertices, va), gather_rows(vertices, vb), gather_rows(sdf, va),
                                  gather_rows(sdf, vb))

    local = torch.full_like(ends_a, -1)
    local[crossing] = slot
    tri_edges = table[case]  # (Ta, 2, 3)
    faces = torch.gather(local, 1, tri_edges.clamp_min(0).reshape(-1, 6)).reshape(-1, 2, 3)
    emitted = torch.arange(2, device=device)[None, :] < count[case][:, None]
    faces = faces[emitted]

    if bool(welded.any()):
        distinct = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
        faces = faces[distinct]
        if faces.shape[0] == 0:
            raise EmptySurfaceError("every surface triangle collapsed onto grid vertices where the SDF is exactly 0 "
                                    "(the outside is only isolated zero points): there is no surface")
        used, faces = torch.unique(faces, return_inverse=True)
        points = gather_rows(points, used)
    return Mesh(points, faces)
