"""Marching tetrahedra: the 16-case table and its winding, one tet at a time; ties (exact zeros weld),
extreme SDF scales and the closed boundary, through DMTet.

Device-aware tests take the ``device`` fixture (``MORPHEUS_TEST_DEVICE=cuda pytest`` for a GPU).
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from morpheus_core.geometry.marching_tets import TRIANGLE_COUNT, marching_tets
from tests.meshes import make_dmtet, signed_volume, sphere, to_trimesh


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("tets")


# ---------------------------------------------------------------- the 16-case table, one tet at a time


@pytest.mark.parametrize("case", range(1, 15))
def test_every_case_separates_inside_from_outside_with_outward_winding(case: int) -> None:
    g = torch.Generator().manual_seed(case)
    tet = torch.tensor([[0, 1, 2, 3]])
    for _ in range(25):
        v = torch.randn(4, 3, generator=g, dtype=torch.float64)
        if torch.linalg.det(v[1:] - v[:1]) < 0:
            v = v[[0, 2, 1, 3]]
        inside = torch.tensor([(case >> c) & 1 for c in range(4)], dtype=torch.bool)
        mag = 0.05 + torch.rand(4, generator=g, dtype=torch.float64)
        sdf = torch.where(inside, -mag, mag)
        mesh = marching_tets(v, tet, sdf)
        assert mesh.num_faces == TRIANGLE_COUNT[case] == (2 if int(inside.sum()) == 2 else 1)
        assert mesh.num_vertices == (4 if mesh.num_faces == 2 else 3)
        # The crossings are zeros of the linear interpolant of the SDF over the tet.
        coef = torch.linalg.solve(torch.cat([v, torch.ones(4, 1, dtype=v.dtype)], 1), sdf)
        values = mesh.vertices @ coef[:3] + coef[3]
        assert values.abs().max() < 1e-12
        n = mesh.face_normals(normalize=True)
        q = mesh.face_vertices()[:, 0]
        side = ((v[None] - q[:, None]) * n[:, None]).sum(-1)  # (F, 4): signed distance of corners
        assert (side[:, inside] < 0).all() and (side[:, ~inside] > 0).all()
        if mesh.num_faces == 2:  # the quad's two halves share their diagonal in opposite directions
            e0 = {(int(a), int(b)) for a, b in mesh.faces[0, [[0, 1], [1, 2], [2, 0]]]}
            e1 = {(int(b), int(a)) for a, b in mesh.faces[1, [[0, 1], [1, 2], [2, 0]]]}
            assert len(e0 & e1) == 1


# ---------------------------------------------------------------- ties, extremes, the closed boundary


def test_plane_through_grid_vertices_welds_to_an_exact_box(cache_dir: Path, device: torch.device) -> None:
    model = make_dmtet(8, cache_dir, device)
    with pytest.warns(RuntimeWarning, match="boundary"):
        model.init_from_sdf(lambda p: p[:, 2])  # zero exactly on the z = 0 layer of vertices
    assert (model.sdf == 0).sum() == 81
    mesh = model().to("cpu")
    area = torch.linalg.cross(*(mesh.face_vertices()[:, 1:] - mesh.face_vertices()[:, :1]).unbind(1), dim=-1)
    assert torch.isfinite(mesh.vertices).all()
    assert area.norm(dim=-1).min() > 1e-4  # no zero-area triangles after welding
    counts = mesh.topology.edge_counts
    assert (counts == 2).all()
    tm = to_trimesh(mesh)
    assert tm.is_winding_consistent
    # Every vertex next to an inside one is exactly 0, so the inside is exactly the union of the tets
    # with an inside corner: [-1,1]²×[-1,0] with its box edges chamfered by the closed boundary.
    inside = (model.effective_sdf() < 0).cpu()[model.tets.cpu()].any(1)
    p = model.grid_vertices.cpu().double()[model.tets.cpu()[inside]]
    expected = float(torch.linalg.det(p[:, 1:] - p[:, :1]).sum() / 6)
    assert 3.5 < expected < 4.0
    assert signed_volume(mesh) == pytest.approx(expected, rel=1e-6)
    assert float(mesh.vertices.detach()[:, 2].max()) == pytest.approx(0.0, abs=1e-6)
    # Welded vertices are grid vertices: every output vertex coincides with one.
    assert set(np.round(mesh.vertices.detach().numpy() * 4).ravel().tolist()) <= set(range(-4, 5))


def test_sphere_with_exact_zeros_at_vertices(cache_dir: Path) -> None:
    model = make_dmtet(16, cache_dir, dtype=torch.float64)
    model.init_from_sdf(sphere(0.75))  # 0.75² = 0.5² + 0.5² + 0.25²: many vertices exactly on it
    zeros = int((model.sdf == 0).sum())
    assert zeros >= 24
    mesh = model()
    assert torch.isfinite(mesh.vertices).all()
    fv = mesh.face_vertices().detach()
    area = torch.linalg.cross(fv[:, 1] - fv[:, 0], fv[:, 2] - fv[:, 0], dim=-1).norm(dim=-1)
    assert area.min() > 1e-8
    counts = mesh.topology.edge_counts
    assert (counts == 2).all()
    assert to_trimesh(mesh).is_winding_consistent
    assert abs(signed_volume(mesh) / (4 / 3 * math.pi * 0.75**3) - 1) < 0.05
    w = torch.randn(mesh.vertices.shape, dtype=torch.float64)
    (mesh.vertices * w).sum().backward()
    assert torch.isfinite(model.sdf.grad).all() and torch.isfinite(model.deform.grad).all()


@pytest.mark.parametrize("scale", [1e-30, 1e-12, 1e12, 1e30])
def test_sdf_scale_does_not_change_the_mesh(scale: float, cache_dir: Path) -> None:
    model = make_dmtet(10, cache_dir)
    model.init_from_sdf(sphere(0.55))
    ref = model()
    with torch.no_grad():
        model.sdf.mul_(scale)
    mesh = model()
    assert torch.equal(mesh.faces, ref.faces)
    torch.testing.assert_close(mesh.vertices, ref.vertices, atol=1e-6, rtol=0)
    mesh.vertices.sum().backward()
    assert torch.isfinite(model.sdf.grad).all()


def test_shape_larger_than_the_box_is_capped_and_closed(cache_dir: Path) -> None:
    model = make_dmtet(10, cache_dir)
    with pytest.warns(RuntimeWarning, match="reaches the tet grid's boundary"):
        model.init_from_sdf(sphere(1.2))
    mesh = model()
    assert (mesh.vertices.abs() <= 1.0 + 1e-6).all()
    counts = mesh.topology.edge_counts
    assert (counts == 2).all()
    assert to_trimesh(mesh).is_watertight
    # Without closing, the surface runs into the box and stays open.
    open_model = make_dmtet(10, cache_dir, close_boundary=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        open_model.init_from_sdf(sphere(1.2))
    counts = open_model().topology.edge_counts
    assert (counts == 1).any()
