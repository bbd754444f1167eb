"""Triangle meshes as tensors: the one mesh type shared by DMTet, the rasteriser and the export."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from morpheus_core.runtime.gather import gather_rows
from morpheus_core.vectors import safe_normalize


class MeshIndexError(ValueError):
    """A face list that is not (F, 3) int64 or indexes outside [0, number of vertices)."""


@dataclass(frozen=True)
class MeshTopology:
    """The connectivity of a face list, computed once and shared by everything that needs it (the
    rasteriser's index check and silhouette edges, the Laplacian and normal-consistency regularisers,
    the watertight check): ``faces`` (F, 3) int64 checked to index ``num_vertices`` vertices, the
    unique undirected edges ``edge_vertices`` (E, 2) with i < j, up to two adjacent faces
    ``edge_faces`` (E, 2) (-1 where absent) and ``edge_counts`` (E,), the faces per edge (2 everywhere
    on a closed manifold). ``faces_version`` is the faces tensor's version counter when this was
    built: a user that changes the faces in place gets a new topology (``Mesh.topology``) or an error
    (the rasteriser), never a stale one."""

    faces: Tensor
    num_vertices: int
    edge_vertices: Tensor
    edge_faces: Tensor
    edge_counts: Tensor
    faces_version: int

    @property
    def nonmanifold(self) -> Tensor:
        """(E,) edges shared by more than two faces."""
        return self.edge_counts > 2

    @property
    def interior(self) -> Tensor:
        """(E,) edges with exactly two faces: the ones with a dihedral angle."""
        return self.edge_counts == 2

    def is_current(self) -> bool:
        return self.faces_version == _version(self.faces)


def _version(faces: Tensor) -> int:
    # Inference tensors keep no version counter (and cannot be changed in place outside inference mode).
    return -1 if faces.is_inference() else faces._version


def mesh_topology(faces: Tensor, num_vertices: int) -> MeshTopology:
    """Check ``faces`` (F, 3) int64 against ``num_vertices`` and find its unique edges (one sort of
    packed 1-D keys). Two host reads: the index range, then the edge count (the GPU is idle by then)."""
    if faces.dim() != 2 or faces.shape[-1] != 3:
        raise MeshIndexError(f"faces must be (F, 3), got {tuple(faces.shape)}")
    if faces.dtype != torch.int64:
        raise MeshIndexError(f"faces must be int64, got {faces.dtype}")
    num_faces, device = faces.shape[0], faces.device
    version = _version(faces)
    if num_faces == 0:
        empty = torch.zeros(0, 2, dtype=torch.int64, device=device)
        return MeshTopology(faces, num_vertices, empty, empty.clone(), torch.zeros(0, dtype=torch.int64,
                                                                                   device=device), version)
    a = faces.reshape(-1)
    b = faces.roll(-1, 1).reshape(-1)  # corners 1, 2, 0; a list index would be a host copy (a sync)
    lo, hi = torch.minimum(a, b), torch.maximum(a, b)
    lowest, highest = torch.stack([lo.min(), hi.max()]).tolist()  # the index check's one host read
    if lowest < 0 or highest >= num_vertices:
        raise MeshIndexError(f"face indices must lie in [0, {num_vertices}), got [{lowest}, {highest}]")
    keys, order = torch.sort(lo * num_vertices + hi, stable=True)
    owner = torch.arange(num_faces, device=device).repeat_interleave(3)[order]
    unique, counts = torch.unique_consecutive(keys, return_counts=True)
    first = torch.cumsum(counts, 0) - counts
    second = torch.where(counts >= 2, owner[(first + 1).clamp(max=keys.numel() - 1)], -1)
    return MeshTopology(faces, num_vertices, torch.stack([unique // num_vertices, unique % num_vertices], 1),
                        torch.stack([owner[first], second], 1), counts, version)


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

    @property
    def topology(self) -> MeshTopology:
        """Edges and index check, built on first use and kept with the mesh: the texture stage renders
        one mesh for thousands of steps, the DMTet stage renders and regularises each step's mesh with
        one edge sort. Rebuilt if the faces were changed in place."""
        cached = self.__dict__.get("_topology")
        if cached is None or not cached.is_current():
            cached = mesh_topology(self.faces, self.num_vertices)
            object.__setattr__(self, "_topology", cached)  # a cache, not state: frozen for the fields only
        return cached

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


# --- Geometry regularisers (DMTet stage: Laplacian smoothness, normal consistency). The SDF sign-change
# regulariser acts on the tet grid, not on a mesh: it lives in tet_surface.py. Both read the mesh's one
# ``topology``; neither selects with a boolean mask, which would read its size on the host every step.


def interior_face_pairs(mesh: Mesh) -> Tensor:
    """(Ei, 2) int64: the two faces of every edge used by exactly two faces.

    Boundary edges (one face) and non-manifold edges (three or more) have no single dihedral
    angle and are left out.
    """
    topo = mesh.topology
    return topo.edge_faces[topo.interior]


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
    topo = mesh.topology
    edges = topo.edge_vertices
    v = mesh.vertices
    src = torch.cat([edges[:, 0], edges[:, 1]])
    dst = torch.cat([edges[:, 1], edges[:, 0]])
    degree = torch.zeros(mesh.num_vertices, dtype=v.dtype, device=v.device).index_add(0, src, torch.ones_like(
        src, dtype=v.dtype))
    neighbour_sum = torch.zeros_like(v).index_add(0, src, gather_rows(v, dst))
    delta = v - neighbour_sum / degree.clamp_min(1.0).unsqueeze(-1)
    keep = degree > 0
    if skip_boundary:
        boundary = (topo.edge_counts == 1).to(v.dtype).repeat_interleave(2)
        keep = keep & (torch.zeros_like(degree).index_add(0, edges.reshape(-1), boundary) == 0)
    # A weighted mean over the kept vertices rather than a boolean selection of them: the selection
    # would read its size on the host every step; no vertex kept gives 0 (with a graph).
    squared = torch.where(keep, (delta ** 2).sum(-1), 0.0)
    return squared.sum() / keep.sum().clamp_min(1).to(v.dtype)


def normal_consistency(mesh: Mesh) -> Tensor:
    """Mean over interior edges of 1 − cos(angle between the two adjacent face normals).

    0 for a flat (consistently wound) mesh, 2 for a fold-over. A degenerate (zero-area) face has
    a zero normal and contributes 1 with a finite gradient.
    """
    if mesh.num_faces == 0:
        return _zero_loss(mesh)
    topo = mesh.topology
    n = mesh.face_normals(normalize=True)
    cos = (gather_rows(n, topo.edge_faces[:, 0]) * gather_rows(n, topo.edge_faces[:, 1].clamp(min=0))).sum(-1)
    # A weighted mean over interior edges; none gives 0 (with a graph).
    interior = topo.interior
    return torch.where(interior, 1.0 - cos, 0.0).sum() / interior.sum().clamp_min(1).to(cos.dtype)
