"""Triangle meshes as tensors: the one mesh type shared by DMTet, the rasteriser and the export."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from morpheus_core.gather import gather_rows

# Normalising a zero-length normal (degenerate face, isolated vertex) must not produce NaN.
_NORMAL_EPS = 1e-20


def safe_normalize(v: Tensor, eps: float = _NORMAL_EPS) -> Tensor:
    """v / |v| along the last dim; zero vectors stay zero and their gradient stays finite."""
    return v * torch.rsqrt((v * v).sum(-1, keepdim=True).clamp_min(eps))


@dataclass(frozen=True)
class Mesh:
    """``vertices`` (V, 3) float, ``faces`` (F, 3) int64, counter-clockwise seen from outside."""

    vertices: Tensor
    faces: Tensor

    def __post_init__(self) -> None:
        if self.vertices.dim() != 2 or self.vertices.shape[-1] != 3:
            raise ValueError(f"vertices must be (V, 3), got {tuple(self.vertices.shape)}")
        if self.faces.dim() != 2 or self.faces.shape[-1] != 3:
            raise ValueError(f"faces must be (F, 3), got {tuple(self.faces.shape)}")
        if self.faces.dtype != torch.int64:
            raise TypeError(f"faces must be int64, got {self.faces.dtype}")

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    def face_vertices(self) -> Tensor:
        """(F, 3, 3): the corner positions of every face."""
        return gather_rows(self.vertices, self.faces)

    def face_normals(self, normalize: bool = True) -> Tensor:
        """(F, 3) outward normals (right-hand rule on the winding); area-weighted if not normalised."""
        v = self.face_vertices()
        n = torch.linalg.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0], dim=-1)
        return safe_normalize(n) if normalize else n

    def vertex_normals(self) -> Tensor:
        """(V, 3) area-weighted average of the adjacent face normals."""
        fn = self.face_normals(normalize=False)
        vn = torch.zeros_like(self.vertices)
        for corner in range(3):
            vn = vn.index_add(0, self.faces[:, corner], fn)
        return safe_normalize(vn)

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Mesh:
        return Mesh(self.vertices.to(device=device, dtype=dtype), self.faces.to(device=device))


# --- Connectivity and geometry regularisers (DMTet stage: Laplacian smoothness, normal consistency).
# The SDF sign-change regulariser acts on the tet grid, not on a mesh: it lives in tet_surface.py.
# Topology changes every step as the SDF moves, so adjacency is recomputed per call (sorts, O(F log F)).


def _face_edge_keys(faces: Tensor, num_vertices: int) -> Tensor:
    """(3F,) int64 key min·V + max of the undirected edge k of face f at position 3f + k."""
    a = faces
    b = faces.roll(-1, dims=1)
    return (torch.minimum(a, b) * num_vertices + torch.maximum(a, b)).reshape(-1)


def unique_edges(mesh: Mesh) -> Tensor:
    """(E, 2) int64 undirected edges, i < j, each once."""
    keys = torch.unique(_face_edge_keys(mesh.faces, mesh.num_vertices))
    return torch.stack([torch.div(keys, mesh.num_vertices, rounding_mode="floor"), keys % mesh.num_vertices], -1)


def edge_face_counts(mesh: Mesh) -> tuple[Tensor, Tensor]:
    """Unique edges (E, 2) and how many faces use each: 2 everywhere on a closed manifold."""
    keys, counts = torch.unique(_face_edge_keys(mesh.faces, mesh.num_vertices), return_counts=True)
    v = mesh.num_vertices
    return torch.stack([torch.div(keys, v, rounding_mode="floor"), keys % v], -1), counts


def interior_face_pairs(mesh: Mesh) -> Tensor:
    """(Ei, 2) int64: the two faces of every edge used by exactly two faces.

    Boundary edges (one face) and non-manifold edges (three or more) have no single dihedral
    angle and are left out.
    """
    keys = _face_edge_keys(mesh.faces, mesh.num_vertices)
    order = torch.argsort(keys, stable=True)
    _, counts = torch.unique_consecutive(keys[order], return_counts=True)
    starts = torch.cumsum(counts, 0) - counts
    first = starts[counts == 2]
    face_of = torch.div(order, 3, rounding_mode="floor")
    return torch.stack([face_of[first], face_of[first + 1]], -1)


def surface_area(mesh: Mesh) -> Tensor:
    """Total area (a 0-d tensor, differentiable): with ``suggest_resolution`` it sizes the DMTet grid."""
    return 0.5 * mesh.face_normals(normalize=False).norm(dim=-1).sum()


def _zero_loss(mesh: Mesh) -> Tensor:
    # Keeps the graph (and the dtype/device) so callers can always .backward() a sum of losses.
    return mesh.vertices.sum() * 0.0


def laplacian_smoothness(mesh: Mesh, skip_boundary: bool = False) -> Tensor:
    """Mean over vertices of |v − mean(neighbours of v)|² (uniform Laplacian).

    Zero for the interior of a flat mesh whose vertex stars are symmetric (a regular grid). It
    also penalises irregular spacing in the tangent plane, which keeps the triangles even.
    Vertices without neighbours are ignored; ``skip_boundary`` ignores vertices on boundary
    edges too, whose one-sided stars are never balanced (closed DMTet meshes have none).
    """
    if mesh.num_faces == 0:
        return _zero_loss(mesh)
    edges, counts = edge_face_counts(mesh)
    v = mesh.vertices
    src = torch.cat([edges[:, 0], edges[:, 1]])
    dst = torch.cat([edges[:, 1], edges[:, 0]])
    degree = torch.zeros(mesh.num_vertices, dtype=v.dtype, device=v.device).index_add(0, src, torch.ones_like(
        src, dtype=v.dtype))
    neighbour_sum = torch.zeros_like(v).index_add(0, src, gather_rows(v, dst))
    delta = v - neighbour_sum / degree.clamp_min(1.0).unsqueeze(-1)
    keep = degree > 0
    if skip_boundary:
        on_boundary = torch.zeros_like(keep)
        on_boundary[edges[counts == 1].reshape(-1)] = True
        keep = keep & ~on_boundary
    # A weighted mean over the kept vertices rather than a boolean selection of them: the selection
    # would read its size on the host every step; no vertex kept gives 0 (with a graph).
    squared = torch.where(keep, (delta ** 2).sum(-1), 0.0)
    return squared.sum() / keep.sum().clamp_min(1).to(v.dtype)


def normal_consistency(mesh: Mesh) -> Tensor:
    """Mean over interior edges of 1 − cos(angle between the two adjacent face normals).

    0 for a flat (consistently wound) mesh, 2 for a fold-over. A degenerate (zero-area) face has
    a zero normal and contributes 1 with a finite gradient.
    """
    pairs = interior_face_pairs(mesh) if mesh.num_faces else None
    if pairs is None or pairs.shape[0] == 0:
        return _zero_loss(mesh)
    n = mesh.face_normals(normalize=True)
    cos = (gather_rows(n, pairs[:, 0]) * gather_rows(n, pairs[:, 1])).sum(-1)
    return (1.0 - cos).mean()
