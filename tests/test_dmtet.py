"""DMTet: the sphere at grid 64, the face budget, gradients, guards, init from a density, the SDF
sign-change regulariser, the state dict (the case table and ties: ``tests/test_marching_tets.py``).

Device-aware tests take the ``device`` fixture (``MORPHEUS_TEST_DEVICE=cuda pytest`` for a GPU).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.func import functional_call

from morpheus_core.geometry.marching_tets import (
    EmptySurfaceError,
    NonFiniteFieldError,
    marching_tets,
    require_surface,
)
from morpheus_core.geometry.mesh import Mesh, surface_area
from morpheus_core.geometry.tet_surface import (
    FACES_PER_CELL_AREA,
    DMTetConfig,
    estimate_faces,
    sdf_sign_change_loss,
    suggest_resolution,
)
from tests.meshes import make_dmtet, signed_volume, sphere, to_trimesh


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("tets")


def _detached(mesh: Mesh) -> Mesh:
    return Mesh(mesh.vertices.detach(), mesh.faces)


# ---------------------------------------------------------------- the sphere at grid 64


def test_sphere_at_grid_64_is_watertight_outward_and_accurate(cache_dir: Path, device: torch.device) -> None:
    r, res = 0.6, 64
    model = make_dmtet(res, cache_dir, device)
    model.init_from_sdf(sphere(r))
    mesh = model()
    assert mesh.vertices.device.type == device.type and torch.isfinite(mesh.vertices).all()
    mesh = mesh.to("cpu")
    counts = mesh.topology.edge_counts
    assert (counts == 2).all()  # closed 2-manifold edges
    edges = mesh.topology.edge_vertices
    assert mesh.num_vertices - edges.shape[0] + mesh.num_faces == 2  # Euler: a topological sphere
    tm = to_trimesh(mesh)
    assert tm.is_watertight and tm.is_winding_consistent
    # No duplicate and no unused vertices.
    assert len(np.unique(tm.vertices, axis=0)) == mesh.num_vertices
    assert torch.unique(mesh.faces).numel() == mesh.num_vertices
    # Outward: every face normal points away from the centre, and the signed volume is positive.
    n = mesh.face_normals(normalize=True).detach()
    centroid = mesh.face_vertices().detach().mean(1)
    assert ((n * centroid).sum(-1) > 0).all()
    exact = 4 / 3 * math.pi * r**3
    vol = signed_volume(mesh)
    assert vol > 0 and abs(vol / exact - 1) < 0.03
    assert abs(tm.volume / exact - 1) < 0.03
    # Crossings of a linearly interpolated exact SDF lie on chords: within a fraction of a cell.
    radius = mesh.vertices.detach().double().norm(dim=-1)
    assert (radius - r).abs().max() < 0.1 * model.config.cell_size
    expected_faces = estimate_faces(res, 4 * math.pi * r**2)
    assert abs(mesh.num_faces / expected_faces - 1) < 0.05


def test_face_count_grows_with_resolution_squared(cache_dir: Path) -> None:
    faces = {}
    for res in (16, 32):
        model = make_dmtet(res, cache_dir)
        model.init_from_sdf(sphere(0.55))
        faces[res] = model().num_faces
    assert 3.6 < faces[32] / faces[16] < 4.4
    # The budget helper, fed the area of a coarse extraction, picks a resolution whose mesh lands
    # near the budget and not far above it.
    area = float(surface_area(_detached(model())))
    assert area == pytest.approx(4 * math.pi * 0.55**2, rel=0.02)
    res = suggest_resolution(12_000, surface_area=area)
    model = make_dmtet(res, cache_dir)
    model.init_from_sdf(sphere(0.55))
    got = model().num_faces
    assert 0.8 * 12_000 < got < 1.08 * 12_000
    assert suggest_resolution(50_000) > suggest_resolution(20_000) >= 8
    assert suggest_resolution(10**9) == 512 and suggest_resolution(1) == 8
    assert FACES_PER_CELL_AREA == pytest.approx(9.0)


# ---------------------------------------------------------------- gradients


def test_gradients_match_finite_differences_in_sdf_and_deformation(cache_dir: Path) -> None:
    model = make_dmtet(3, cache_dir, dtype=torch.float64, close_boundary=False)
    g = torch.Generator().manual_seed(7)
    base_sdf = (model.grid_vertices.norm(dim=-1) - 0.75 + 0.1 * torch.randn(model.num_vertices, generator=g,
                                                                             dtype=torch.float64))
    base_deform = 0.5 * torch.randn(model.num_vertices, 3, generator=g, dtype=torch.float64)
    weights = None

    def verts(sdf: torch.Tensor, deform: torch.Tensor) -> torch.Tensor:
        return functional_call(model, {"sdf": sdf, "deform": deform}, ()).vertices

    weights = torch.randn(verts(base_sdf, base_deform).shape, generator=g, dtype=torch.float64)

    def scalar(sdf: torch.Tensor, deform: torch.Tensor) -> torch.Tensor:
        return (verts(sdf, deform) * weights).sum()

    sdf = base_sdf.clone().requires_grad_(True)
    deform = base_deform.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(scalar, (sdf, deform), eps=1e-6, atol=1e-7, rtol=1e-5)
    assert torch.autograd.gradcheck(verts, (sdf, deform), eps=1e-6, atol=1e-7, rtol=1e-5)
    scalar(sdf, deform).backward()
    assert sdf.grad.abs().max() > 0 and deform.grad.abs().max() > 0


def test_gradients_flow_on_device(cache_dir: Path, device: torch.device) -> None:
    model = make_dmtet(12, cache_dir, device)
    model.init_from_sdf(sphere(0.5))
    mesh = model()
    w = torch.randn(mesh.vertices.shape, generator=torch.Generator().manual_seed(0)).to(device)
    (mesh.vertices * w).sum().backward()
    assert torch.isfinite(model.sdf.grad).all() and torch.isfinite(model.deform.grad).all()
    near = model.sdf.grad != 0
    assert near.any() and (model.deform.grad != 0).any()
    # Only vertices of crossing edges move the surface.
    assert (model.sdf.detach()[near].abs() <= math.sqrt(3) * model.config.cell_size + 1e-6).all()


def test_deformation_is_bounded_by_scale_cells(cache_dir: Path) -> None:
    model = make_dmtet(8, cache_dir, deform_scale=0.3)
    with torch.no_grad():
        model.deform.copy_(torch.randn(model.deform.shape, generator=torch.Generator().manual_seed(1)) * 100)
    offset = model.vertex_positions() - model.grid_vertices
    assert offset.abs().max() <= 0.3 * model.config.cell_size * (1 + 1e-6)
    assert offset.abs().max() > 0.29 * model.config.cell_size
    with torch.no_grad():
        model.deform.zero_()
    assert torch.equal(model.vertex_positions(), model.grid_vertices)


# ---------------------------------------------------------------- guards


def test_empty_and_full_sdf_raise_a_clear_error(cache_dir: Path, device: torch.device) -> None:
    model = make_dmtet(6, cache_dir, device)
    with torch.no_grad():
        model.sdf.fill_(0.3)
    with pytest.raises(EmptySurfaceError, match="everything is outside"):
        model()
    with torch.no_grad():
        model.sdf.fill_(-0.3)
    with pytest.raises(EmptySurfaceError, match="everything is inside"):
        model()
    with torch.no_grad():
        model.sdf.zero_()  # all exactly 0: outside by the tie rule
    with pytest.raises(EmptySurfaceError):
        model()
    assert issubclass(EmptySurfaceError, ValueError)
    # Inside everywhere but one vertex at exactly 0: every triangle collapses onto it.
    solid = make_dmtet(6, cache_dir, device, close_boundary=False)
    with torch.no_grad():
        solid.sdf.fill_(-0.3)
        solid.sdf[solid.num_vertices // 2] = 0.0
    with pytest.raises(EmptySurfaceError, match="collapsed"):
        solid()
    with pytest.raises(EmptySurfaceError):
        model.init_from_sdf(lambda p: p.norm(dim=-1) + 1.0)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
@pytest.mark.parametrize("where", ["sdf", "deform"])
def test_non_finite_parameters_raise(bad: float, where: str, cache_dir: Path) -> None:
    model = make_dmtet(6, cache_dir)
    with torch.no_grad():
        getattr(model, where).view(-1)[5] = bad
    with pytest.raises(NonFiniteFieldError, match=f"DMTet {where}"):
        model()


def test_surface_checks_name_what_failed(cache_dir: Path) -> None:
    model = make_dmtet(6, cache_dir)
    with torch.no_grad():  # inside only on the boundary: the closed boundary leaves nothing inside
        model.sdf.copy_(torch.where(model.boundary, -0.3, 0.3))
    with pytest.raises(EmptySurfaceError, match="DMTet sdf with its boundary closed is ≥ 0 at all"):
        model()
    open_model = make_dmtet(6, cache_dir, close_boundary=False)
    with torch.no_grad():
        open_model.sdf.copy_(model.sdf)
    assert open_model().num_faces > 0
    # Several failures at once: the first in order is named, finiteness before the sign change.
    gen = torch.Generator().manual_seed(11)
    sdf, other = torch.rand(50, generator=gen) + 0.1, torch.randn(50, 3, generator=gen)
    other[7, 1] = float("nan")
    with pytest.raises(NonFiniteFieldError, match="second has 1 non-finite"):
        require_surface({"first": other[:, 0], "second": other, "third": other}, {"sdf": sdf})
    with pytest.raises(EmptySurfaceError, match="sdf is ≥ 0 at all 50"):
        require_surface({"first": sdf}, {"sdf": sdf, "negated": -sdf})
    require_surface({"first": sdf}, {"mixed": sdf - 0.6})


def test_density_threshold_errors_name_the_threshold(cache_dir: Path) -> None:
    model = make_dmtet(6, cache_dir)
    blob = lambda p: 40.0 * torch.exp(-(p * p).sum(-1) / 0.1)  # noqa: E731
    with pytest.raises(EmptySurfaceError, match="threshold 50 is too high"):
        model.init_from_density(blob, threshold=50.0)
    with pytest.raises(EmptySurfaceError, match="threshold -1 is too low"):
        model.init_from_density(blob, threshold=-1.0)
    with pytest.raises(NonFiniteFieldError, match="NaN"):
        model.init_from_density(lambda p: torch.full(p.shape[:1], float("nan")))
    with pytest.raises(ValueError, match="must map"):
        model.init_from_density(lambda p: p)
    before = model.sdf.detach().clone()
    with pytest.raises(EmptySurfaceError):
        model.init_from_density(blob, threshold=1e6)
    assert torch.equal(model.sdf.detach(), before)  # a failed init leaves the parameters alone


def test_config_validation() -> None:
    for kw in ({"resolution": 1}, {"half_extent": 0.0}, {"deform_scale": -0.1}, {"deform_scale": 2.0},
               {"init_clamp_cells": 0.0}):
        with pytest.raises(ValueError):
            DMTetConfig(**kw)


# ---------------------------------------------------------------- initialisation from a density field


def test_init_from_gaussian_density_recovers_the_radius(cache_dir: Path, device: torch.device) -> None:
    amplitude, sigma, threshold = 400.0, 0.3, 25.0
    radius = sigma * math.sqrt(2 * math.log(amplitude / threshold))  # density == threshold there

    def density(p: torch.Tensor) -> torch.Tensor:
        return amplitude * torch.exp(-(p * p).sum(-1) / (2 * sigma**2))

    model = make_dmtet(32, cache_dir, device)
    model.init_from_density(density, threshold=threshold, chunk_size=1000)  # several chunks
    cell = model.config.cell_size
    assert model.sdf.abs().max() <= model.config.init_clamp_cells * cell + 1e-6  # bounded, metric-sized
    mesh = model()
    rho = mesh.vertices.detach().norm(dim=-1)
    assert (rho - radius).abs().max() < cell
    assert abs(float(rho.mean()) - radius) < 0.25 * cell
    # Redistancing keeps every inside/outside decision of the raw density.
    raw_inside = density(model.grid_vertices) > threshold
    assert torch.equal(model.sdf < 0, raw_inside)
    raw_mesh = marching_tets(model.grid_vertices, model.tets, threshold - density(model.grid_vertices))
    assert raw_mesh.num_faces == mesh.num_faces
    assert to_trimesh(mesh.to("cpu")).is_watertight


def test_init_from_density_handles_infinite_density(cache_dir: Path) -> None:
    model = make_dmtet(8, cache_dir)
    model.init_from_density(lambda p: torch.where(p.norm(dim=-1) < 0.5, float("inf"), 0.0), threshold=25.0)
    mesh = model()
    assert torch.isfinite(mesh.vertices).all() and torch.isfinite(model.sdf).all()


# ---------------------------------------------------------------- SDF sign-change regulariser and bookkeeping


def test_sdf_sign_change_loss(cache_dir: Path) -> None:
    model = make_dmtet(6, cache_dir, dtype=torch.float64)
    model.init_from_sdf(sphere(0.5))
    loss = model.sdf_regulariser()
    assert loss > 0 and torch.isfinite(loss)
    loss.backward()
    grad = model.sdf.grad
    a, b = model.edges[:, 0], model.edges[:, 1]
    crossing = (model.sdf[a] < 0) != (model.sdf[b] < 0)
    touched = torch.zeros_like(grad, dtype=torch.bool)
    touched[a[crossing]] = True
    touched[b[crossing]] = True
    assert (grad[~touched] == 0).all() and (grad[touched] != 0).all()
    # Descent shrinks the SDF toward zero around the surface: inside values rise, outside values fall.
    s = model.sdf.detach()
    assert (grad[touched & (s < 0)] < 0).all() and (grad[touched & (s > 0)] > 0).all()
    # Analytic value on one crossing edge: BCE(logit −f_a/s, target 1) + BCE(logit −f_b/s, target 0).
    one = sdf_sign_change_loss(torch.tensor([0.3, -0.1], dtype=torch.float64), torch.tensor([[0, 1]]), 0.5)
    expect = math.log1p(math.exp(0.3 / 0.5)) + math.log1p(math.exp(0.1 / 0.5))
    assert float(one) == pytest.approx(expect, rel=1e-12)
    # No crossing → exactly 0, with a graph.
    sdf = torch.rand(10, dtype=torch.float64, requires_grad=True)
    zero = sdf_sign_change_loss(sdf, torch.tensor([[0, 1], [2, 3]]))
    zero.backward()
    assert float(zero.detach()) == 0.0 and (sdf.grad == 0).all()
    # Non-finite values on edges that do not cross reach neither the loss nor the gradient.
    wild = torch.tensor([0.3, -0.1, float("nan"), float("inf"), -float("inf")], dtype=torch.float64,
                        requires_grad=True)
    kept = sdf_sign_change_loss(wild, torch.tensor([[0, 1], [2, 3], [3, 3], [4, 4]]), 0.5)
    kept.backward()
    assert float(kept) == pytest.approx(expect, rel=1e-12)
    assert torch.isfinite(wild.grad).all() and (wild.grad[2:] == 0).all()
    # Gradient matches finite differences.
    x = torch.randn(8, dtype=torch.float64, generator=torch.Generator().manual_seed(3), requires_grad=True)
    edges = torch.tensor([[0, 1], [1, 2], [2, 3], [4, 5], [5, 6], [6, 7], [0, 7]])
    assert torch.autograd.gradcheck(lambda v: sdf_sign_change_loss(v, edges, 0.7), (x,))
    with pytest.raises(ValueError):
        sdf_sign_change_loss(x, edges, 0.0)


def test_state_dict_holds_only_the_parameters(cache_dir: Path) -> None:
    model = make_dmtet(4, cache_dir)
    assert set(model.state_dict()) == {"sdf", "deform"}
    other = make_dmtet(4, cache_dir)
    model.init_from_sdf(sphere(0.3))
    other.load_state_dict(model.state_dict())
    assert torch.equal(other().faces, model().faces)
