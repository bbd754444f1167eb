"""Laplacian smoothness and normal consistency: analytic values, ideal cases, gradients, degeneracy."""

from __future__ import annotations

import math

import pytest
import torch
import trimesh

from morpheus_core.geometry import mesh as mesh_module
from morpheus_core.geometry.mesh import (
    Mesh,
    MeshIndexError,
    interior_face_pairs,
    laplacian_smoothness,
    mesh_topology,
    normal_consistency,
    surface_area,
)
from morpheus_core.geometry.winding import winding_number


def _grid(n: int, dtype=torch.float64, device="cpu") -> Mesh:
    """Flat n×n square grid in z = 0, each square split along the same diagonal (CCW from +z)."""
    t = torch.linspace(-1, 1, n + 1, dtype=dtype)
    y, x = torch.meshgrid(t, t, indexing="ij")
    v = torch.stack([x.ravel(), y.ravel(), torch.zeros_like(x.ravel())], -1)
    i, j = torch.meshgrid(torch.arange(n), torch.arange(n), indexing="ij")
    a = (i * (n + 1) + j).ravel()
    b, c, d = a + 1, a + n + 2, a + n + 1
    faces = torch.cat([torch.stack([a, b, c], -1), torch.stack([a, c, d], -1)])
    return Mesh(v, faces).to(device)


def _cube() -> Mesh:
    tm = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    return Mesh(torch.tensor(tm.vertices, dtype=torch.float64), torch.tensor(tm.faces, dtype=torch.int64))


def _icosphere(subdivisions: int) -> Mesh:
    tm = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    return Mesh(torch.tensor(tm.vertices, dtype=torch.float64), torch.tensor(tm.faces, dtype=torch.int64))


def _octahedron() -> Mesh:
    v = torch.tensor([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=torch.float64)
    f = torch.tensor([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    return Mesh(v, f)


def test_flat_grid_is_ideal(device: torch.device) -> None:
    mesh = _grid(6, device=device)
    # Tilt and move it: both losses are invariant to rigid motions.
    rot = torch.linalg.matrix_exp(torch.tensor([[0, -0.3, 0.5], [0.3, 0, -0.2], [-0.5, 0.2, 0]],
                                               dtype=torch.float64)).to(device)
    mesh = Mesh(mesh.vertices @ rot.T + torch.tensor([0.2, -1.0, 3.0], dtype=torch.float64, device=device),
                mesh.faces)
    assert float(laplacian_smoothness(mesh, skip_boundary=True)) == pytest.approx(0.0, abs=1e-24)
    assert float(normal_consistency(mesh)) == pytest.approx(0.0, abs=1e-14)
    # The one-sided stars of the rim are not balanced: included, the loss is positive.
    assert float(laplacian_smoothness(mesh)) > 1e-3


def test_known_values() -> None:
    # Octahedron: each vertex's 4 neighbours average to the origin, so |Δv|² = |v|² = 1.
    assert float(laplacian_smoothness(_octahedron())) == pytest.approx(1.0, rel=1e-12)
    # Octahedron: 12 edges, dihedral normals (±1,±1,±1)/√3 differ in one sign: cos = 1/3.
    assert float(normal_consistency(_octahedron())) == pytest.approx(2 / 3, rel=1e-12)
    # Cube: 12 box edges at 90° (1 − cos = 1) and 6 flat face diagonals (0) → 12/18.
    cube = _cube()
    assert interior_face_pairs(cube).shape == (18, 2)
    assert float(normal_consistency(cube)) == pytest.approx(2 / 3, rel=1e-12)
    # A fold-over (two triangles on top of each other with opposite normals) costs the maximum, 2.
    v = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=torch.float64)
    fold = Mesh(v, torch.tensor([[0, 1, 2], [0, 2, 1]]))
    assert float(normal_consistency(fold)) == pytest.approx(2.0)


def test_sphere_smooth_versus_noisy() -> None:
    coarse, fine = _icosphere(2), _icosphere(4)
    nc_coarse, nc_fine = float(normal_consistency(coarse)), float(normal_consistency(fine))
    assert nc_fine < 2e-3 and nc_fine < nc_coarse / 10
    g = torch.Generator().manual_seed(0)
    noise = 1 + 0.02 * torch.randn(fine.num_vertices, 1, generator=g, dtype=torch.float64)
    noisy = Mesh(fine.vertices * noise, fine.faces)
    assert float(laplacian_smoothness(noisy)) > 5 * float(laplacian_smoothness(fine))
    assert float(normal_consistency(noisy)) > 5 * nc_fine


def test_gradients_match_finite_differences() -> None:
    base = _icosphere(1)
    g = torch.Generator().manual_seed(1)
    v0 = base.vertices + 0.05 * torch.randn(base.vertices.shape, generator=g, dtype=torch.float64)
    v = v0.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: laplacian_smoothness(Mesh(x, base.faces)), (v,))
    assert torch.autograd.gradcheck(lambda x: normal_consistency(Mesh(x, base.faces)), (v,))
    grid = _grid(3)
    w = (grid.vertices + 0.1 * torch.randn(grid.vertices.shape, generator=g, dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda x: laplacian_smoothness(Mesh(x, grid.faces), skip_boundary=True), (w,))
    # Descending the Laplacian loss removes the noise: it ends below the clean sphere's own value.
    x = v0.clone().requires_grad_(True)
    opt = torch.optim.SGD([x], lr=5.0)
    for _ in range(20):
        opt.zero_grad()
        laplacian_smoothness(Mesh(x, base.faces)).backward()
        opt.step()
    assert float(laplacian_smoothness(Mesh(x.detach(), base.faces))) < float(laplacian_smoothness(base))
    assert float(laplacian_smoothness(base)) < float(laplacian_smoothness(Mesh(v0, base.faces)))


def test_degenerate_meshes_stay_finite(device: torch.device) -> None:
    # A zero-area face (three equal corners), a sliver, an isolated vertex, a non-manifold edge.
    v = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0.5, 0.5, 0.5], [5, 5, 5], [1, 1, 0]],
                     dtype=torch.float32, device=device)
    v[4] = v[3]  # vertex 4 collapses onto vertex 3
    faces = torch.tensor([[0, 1, 2], [0, 2, 3], [3, 4, 0], [0, 3, 1], [1, 2, 6], [0, 1, 3]], device=device)
    mesh_v = v.clone().requires_grad_(True)
    mesh = Mesh(mesh_v, faces)
    for loss in (laplacian_smoothness(mesh), laplacian_smoothness(mesh, skip_boundary=True),
                 normal_consistency(mesh)):
        assert torch.isfinite(loss)
        (grad,) = torch.autograd.grad(loss, mesh_v)
        assert torch.isfinite(grad).all()
    # The isolated vertex 5 is ignored, not pulled toward the origin.
    (grad,) = torch.autograd.grad(laplacian_smoothness(mesh), mesh_v)
    assert (grad[5] == 0).all()
    # Every vertex on the boundary (an open fan) and skipped: 0, with a graph and zero gradients.
    fan_v = torch.rand(4, 3, generator=torch.Generator().manual_seed(9)).to(device).requires_grad_(True)
    fan = laplacian_smoothness(Mesh(fan_v, torch.tensor([[0, 1, 2], [0, 2, 3]], device=device)), skip_boundary=True)
    (grad,) = torch.autograd.grad(fan, fan_v)
    assert float(fan.detach()) == 0.0 and (grad == 0).all()
    # Nothing at all: 0 with a graph.
    empty = Mesh(torch.rand(4, 3, requires_grad=True), torch.zeros(0, 3, dtype=torch.int64))
    for loss in (laplacian_smoothness(empty), normal_consistency(empty)):
        assert float(loss.detach()) == 0.0
        loss.backward()


def test_connectivity_helpers() -> None:
    sphere = _icosphere(2)
    edges = sphere.topology.edge_vertices
    assert edges.shape[0] == 3 * sphere.num_faces // 2
    assert sphere.num_vertices - edges.shape[0] + sphere.num_faces == 2
    assert (edges[:, 0] < edges[:, 1]).all()
    counts = sphere.topology.edge_counts
    assert (counts == 2).all()
    grid = _grid(4)
    counts = grid.topology.edge_counts
    assert int((counts == 1).sum()) == 16 and int((counts == 2).sum()) == grid.topology.edge_vertices.shape[0] - 16
    # Each interior pair shares exactly one edge.
    pairs = interior_face_pairs(sphere)
    shared = [len(set(sphere.faces[a].tolist()) & set(sphere.faces[b].tolist())) for a, b in pairs.tolist()]
    assert set(shared) == {2} and pairs.shape[0] == edges.shape[0]


def test_laplacian_scales_with_size_squared() -> None:
    sphere = _icosphere(2)
    base = float(laplacian_smoothness(sphere))
    big = float(laplacian_smoothness(Mesh(sphere.vertices * 3, sphere.faces)))
    assert big == pytest.approx(9 * base, rel=1e-10)
    assert math.isfinite(base) and base > 0


def test_surface_area() -> None:
    assert float(surface_area(_grid(5))) == pytest.approx(4.0, rel=1e-12)
    assert float(surface_area(_cube())) == pytest.approx(24.0, rel=1e-12)
    assert float(surface_area(_icosphere(4))) == pytest.approx(4 * math.pi, rel=2e-3)
    v = torch.zeros(3, 3, dtype=torch.float64, requires_grad=True)  # one zero-area triangle
    (grad,) = torch.autograd.grad(surface_area(Mesh(v, torch.tensor([[0, 1, 2]]))), v)
    assert torch.isfinite(grad).all()


def test_winding_number_is_one_inside_and_zero_outside_a_closed_mesh() -> None:
    g = torch.Generator().manual_seed(11)
    box = trimesh.creation.box(extents=(1.0, 0.6, 0.8))
    mesh = Mesh(torch.tensor(box.vertices, dtype=torch.float32), torch.tensor(box.faces, dtype=torch.int64))
    pts = (torch.rand(400, 3, generator=g) * 2 - 1) * 0.9
    inside = (pts.abs() < torch.tensor([0.5, 0.3, 0.4])).all(-1)
    margin = ((pts.abs() - torch.tensor([0.5, 0.3, 0.4])).abs() > 0.02).all(-1)
    w = winding_number(mesh, pts, chunk_pairs=1000)
    assert torch.allclose(w[margin & inside], torch.ones(1), atol=1e-4)
    assert torch.allclose(w[margin & ~inside], torch.zeros(1), atol=1e-4)
    flipped = Mesh(mesh.vertices, mesh.faces.flip(-1))  # inward winding: −1 inside
    assert torch.allclose(winding_number(flipped, pts[margin & inside]), -torch.ones(1), atol=1e-4)


def test_one_topology_per_mesh_serves_render_and_regularisers(monkeypatch: pytest.MonkeyPatch) -> None:
    """A DMTet step renders and regularises one mesh; a texture step renders the same mesh thousands of
    times: the edge sort and index check (host reads on CUDA) happen once per mesh, not per use."""
    from morpheus_core.cameras import orbit
    from morpheus_core.render.mesh_renderer import render_mesh

    built = []
    real = mesh_module.mesh_topology
    monkeypatch.setattr(mesh_module, "mesh_topology", lambda *a: built.append(a) or real(*a))
    mesh = _icosphere(2).to(dtype=torch.float32)
    cams = orbit([10.0, 30.0], [0.0, 120.0])
    for _ in range(3):
        render_mesh(mesh, cams, 24, 24, lambda p: p.abs())
    laplacian_smoothness(mesh), normal_consistency(mesh), interior_face_pairs(mesh)
    assert len(built) == 1
    assert len(Mesh(mesh.vertices, mesh.faces).topology.edge_counts) == 3 * mesh.num_faces // 2
    assert len(built) == 2  # a new mesh is a new topology


def test_topology_rejects_bad_indices_and_matches_a_brute_force_count() -> None:
    g = torch.Generator().manual_seed(3)
    faces = torch.randint(0, 12, (40, 3), generator=g)
    topo = mesh_topology(faces, 12)
    counts = {}
    for f in faces.tolist():
        for k in range(3):
            e = tuple(sorted((f[k], f[(k + 1) % 3])))
            counts[e] = counts.get(e, 0) + 1
    got = {tuple(e): c for e, c in zip(topo.edge_vertices.tolist(), topo.edge_counts.tolist(), strict=True)}
    assert got == counts
    for bad_index, shown in ((12, r"\[0, 12\), got \[0, 12\]"), (-1, r"got \[-1, ")):
        bad = faces.clone()
        bad[5, 1] = bad_index
        with pytest.raises(MeshIndexError, match=shown):
            mesh_topology(bad, 12)
    with pytest.raises(MeshIndexError, match="int64"):
        mesh_topology(faces.int(), 12)


def test_a_mesh_made_in_inference_mode_has_a_topology() -> None:
    with torch.inference_mode():
        mesh = _octahedron()
        assert float(normal_consistency(mesh)) == pytest.approx(2 / 3, rel=1e-12)
    assert mesh.topology.is_current() and mesh.topology.edge_counts.shape == (12,)
