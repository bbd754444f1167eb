"""The mesh renderer: analytic sphere silhouette, normals and depth, alignment with the camera rays,
batching, gradients to vertices and the colour field, and safety on degenerate input."""

from __future__ import annotations

import math

import pytest
import torch
import trimesh
from torch import nn

from morpheus_core.cameras import Cameras, orbit
from morpheus_core.geometry.mesh import Mesh
from morpheus_core.render.mesh_renderer import MeshRenderConfig, render_mesh, render_mesh_groups
from morpheus_core.render.output import RenderOutput


def sphere(subdivisions: int = 4, radius: float = 1.0, device: torch.device | str = "cpu") -> Mesh:
    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return Mesh(torch.tensor(ico.vertices, dtype=torch.float32, device=device),
                torch.tensor(ico.faces, dtype=torch.int64, device=device))


def position_colour(points: torch.Tensor) -> torch.Tensor:
    return 0.5 + 0.4 * torch.sin(2.0 * points + torch.tensor([0.0, 1.0, 2.0], device=points.device))


def pixel_ndc(height: int, width: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    xs = (2 * torch.arange(width, device=device) + 1) / width - 1
    ys = 1 - (2 * torch.arange(height, device=device) + 1) / height
    return xs.expand(height, width), ys[:, None].expand(height, width)


def test_unit_sphere_opacity_is_the_analytic_disc(device: torch.device) -> None:
    """Seen from distance d, a unit sphere's outline is a circle of NDC radius tan(asin(1/d)) / tan(fov/2)."""
    size, distance, fov = 96, 4.0, 40.0
    cams = orbit([0.0, 30.0, -40.0], [0.0, 75.0, -150.0], distance=distance, fov_deg=fov)
    out = render_mesh(sphere(4, device=device), cams, size, size, position_colour, background=0.25)
    radius = math.tan(math.asin(1.0 / distance)) / math.tan(math.radians(fov / 2))
    x, y = pixel_ndc(size, size, device)
    r = torch.sqrt(x**2 + y**2)
    pixel = 2.0 / size
    opacity = out.opacity[..., 0]
    assert out.opacity.dtype == torch.float32 and out.rgb.dtype == torch.float32
    assert (opacity[:, r < radius - 1.5 * pixel] == 1).all()
    assert (opacity[:, r > radius + 1.5 * pixel] == 0).all()
    assert ((opacity >= 0) & (opacity <= 1)).all()
    disc_area = math.pi * (radius / pixel) ** 2  # in pixels
    assert torch.allclose(opacity.sum((1, 2)), torch.full((3,), disc_area, device=device), rtol=4e-3)
    # Background pixels show the background colour; the fully covered ones the field's colour.
    assert torch.allclose(out.rgb[:, r > radius + 1.5 * pixel], torch.tensor(0.25, device=device))


def test_normals_face_the_camera_and_depth_is_camera_distance(device: torch.device) -> None:
    size, distance = 64, 4.0
    cams = orbit([20.0, -10.0], [40.0, 170.0], distance=distance)
    for mode in ("vertex", "face"):
        out = render_mesh(sphere(4, device=device), cams, size, size, position_colour,
                          config=MeshRenderConfig(normals=mode))
        centre = out.normal[:, size // 2 - 1: size // 2 + 1, size // 2 - 1: size // 2 + 1]
        towards_camera = cams.positions.to(device) / distance
        cos = (centre * towards_camera[:, None, None]).sum(-1)
        assert (cos > (0.999 if mode == "vertex" else 0.99)).all()
        covered = out.opacity[..., 0] == 1
        assert torch.allclose(out.normal[covered].norm(dim=-1), torch.ones((), device=device), atol=1e-5)
        assert (out.normal[out.opacity[..., 0] == 0] == 0).all()
        centre_depth = out.depth[:, size // 2 - 1: size // 2 + 1, size // 2 - 1: size // 2 + 1]
        assert torch.allclose(centre_depth, torch.full_like(centre_depth, distance - 1.0), atol=5e-3)


def test_surface_points_lie_on_the_camera_rays(device: torch.device) -> None:
    """Mesh renders line up with NeRF renders: origin + depth · ray direction hits the rendered surface."""
    cams = orbit([25.0], [-60.0], distance=3.0)
    out = render_mesh(sphere(5, radius=0.8, device=device), cams, 40, 52, position_colour)
    origins, dirs = cams.to(device).rays(40, 52)
    covered = out.opacity[..., 0] == 1
    points = origins + out.depth * dirs
    assert torch.allclose(points[covered].norm(dim=-1), torch.full((int(covered.sum()),), 0.8, device=device),
                          atol=2e-3)
    assert covered.sum() > 300


def test_batch_equals_separate_renders(device: torch.device) -> None:
    cams = orbit([0.0, 35.0, -20.0], [10.0, 100.0, -90.0])
    mesh = sphere(3, radius=0.7, device=device)
    batched = render_mesh(mesh, cams, 32, 40, position_colour, background=torch.tensor([0.1, 0.2, 0.3]))
    for i in range(3):
        single = render_mesh(mesh, cams[i], 32, 40, position_colour, background=torch.tensor([0.1, 0.2, 0.3]))
        for name in ("rgb", "opacity", "depth", "normal"):
            # The batched projection rounds differently from the single one: float32 noise only.
            assert torch.allclose(getattr(batched, name)[i: i + 1], getattr(single, name), atol=2e-5)


def test_camera_groups_render_as_separate_batches(device: torch.device) -> None:
    g = torch.Generator().manual_seed(21)
    ref = orbit(float(torch.rand(1, generator=g)) * 30.0, 15.0)
    novel = orbit((torch.rand(3, generator=g) * 60 - 30).tolist(), (torch.rand(3, generator=g) * 360).tolist())
    mesh = sphere(3, radius=0.6, device=device)
    mesh = Mesh(mesh.vertices + 0.05 * torch.randn(mesh.vertices.shape, generator=g).to(device), mesh.faces)
    mesh.vertices.requires_grad_(True)
    one, many = render_mesh_groups(mesh, [ref, novel], 24, 28, position_colour)
    assert one.rgb.shape[0] == 1 and many.rgb.shape[0] == 3
    weights = torch.rand(4, 24, 28, 3, generator=g).to(device)
    (torch.cat([one.rgb, many.rgb]) * weights).sum().backward()
    grad, mesh.vertices.grad = mesh.vertices.grad, None
    apart = [render_mesh(mesh, c, 24, 28, position_colour) for c in (ref, novel)]
    (torch.cat([apart[0].rgb, apart[1].rgb]) * weights).sum().backward()
    for got, want in zip((one, many), apart, strict=True):
        for name in ("rgb", "opacity", "depth", "normal"):
            assert torch.allclose(getattr(got, name), getattr(want, name), atol=2e-5)
    assert torch.allclose(grad, mesh.vertices.grad, atol=1e-4) and float(grad.abs().sum()) > 0
    with pytest.raises(ValueError, match="do not add up"):
        one.split([2])
    with pytest.raises(ValueError, match="one near/far pair"):
        Cameras.cat([ref, Cameras(novel.c2w, novel.fov_y, novel.elevation, novel.azimuth, novel.distance, near=0.5)])
    with pytest.raises(ValueError, match="at least one"):
        Cameras.cat([])
    joined = RenderOutput.cat([one, many])
    for part, back in zip((one, many), joined.split([1, 3]), strict=True):
        for name in ("rgb", "opacity", "depth", "normal"):
            assert torch.equal(getattr(part, name), getattr(back, name))
    with pytest.raises(ValueError, match="at least one render"):
        RenderOutput.cat([])


class TinyField(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        torch.manual_seed(0)
        self.net = nn.Sequential(nn.Linear(3, 16), nn.Tanh(), nn.Linear(16, 3))

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.net(points))


def test_gradients_reach_vertices_at_the_silhouette_and_the_colour_field(device: torch.device) -> None:
    base = sphere(3, radius=0.6, device=device)
    vertices = base.vertices.clone().requires_grad_(True)
    field = TinyField().to(device)
    cams = orbit([10.0, -30.0], [0.0, 120.0])
    out = render_mesh(Mesh(vertices, base.faces), cams, 48, 48, field, background=0.0)
    g = torch.Generator().manual_seed(1)
    target = torch.rand(out.rgb.shape, generator=g).to(device)
    ((out.rgb - target) ** 2).mean().add(out.opacity.mean()).backward()
    assert torch.isfinite(vertices.grad).all()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in field.parameters())
    # Opacity alone: moving vertices outward grows the anti-aliased silhouette, so the gradient of
    # the total opacity along the outward (radial) direction is positive, and only silhouette
    # vertices get one.
    vertices.grad = None
    render_mesh(Mesh(vertices, base.faces), cams[:1], 48, 48, field).opacity.sum().backward()
    radial = (vertices.grad * base.vertices).sum(-1)
    assert radial.sum() > 0 and (radial > 0).sum() > 20
    view_dir = cams.positions[0].to(device) / cams.positions[0].norm()
    facing = (base.vertices @ view_dir) / 0.6  # cos of the angle between vertex and camera direction
    assert (vertices.grad[facing.abs() > 0.5] == 0).all()


def test_degenerate_triangles_and_near_plane_crossings_give_no_nan(device: torch.device) -> None:
    base = sphere(3, radius=0.6, device=device)
    v = base.vertices
    extra = torch.tensor([[0.0, 0.0, 0.0], [0.3, 0.3, 0.3], [0.6, 0.6, 0.6]], device=device)  # collinear
    vertices = torch.cat([v, extra]).requires_grad_(True)
    n = v.shape[0]
    degenerate = torch.tensor([[0, 0, 1], [2, 2, 2], [n, n + 1, n + 2], [3, 4, 3]], device=device)
    mesh = Mesh(vertices, torch.cat([base.faces, degenerate]))
    # The second camera sits inside the sphere: triangles lie behind it and cross w = 0.
    cams = orbit([0.0, 10.0], [0.0, 50.0], distance=[2.5, 0.3])
    homog = torch.cat([v, torch.ones_like(v[:, :1])], 1)
    w = (homog @ cams.world_to_clip()[1].to(device).T)[:, 3][base.faces]
    assert ((w.amin(1) < 0) & (w.amax(1) > 0)).sum() > 10
    out = render_mesh(mesh, cams, 40, 40, position_colour)
    for name in ("rgb", "opacity", "depth", "normal"):
        assert torch.isfinite(getattr(out, name)).all()
    (out.rgb.sum() + out.opacity.sum() + out.depth.sum() + out.normal.sum()).backward()
    assert torch.isfinite(vertices.grad).all()
    assert out.opacity[1].sum() > 0  # the near view still draws the triangles fully in front


def test_bad_colour_field_and_background_raise() -> None:
    cams = orbit([0.0], [0.0])
    with pytest.raises(ValueError, match="colour_fn"):
        render_mesh(sphere(1), cams, 16, 16, lambda p: p[:, :2])
    with pytest.raises(ValueError, match="background"):
        render_mesh(sphere(1), cams, 16, 16, position_colour, background=torch.zeros(2))
    with pytest.raises(ValueError, match="normals"):
        MeshRenderConfig(normals="smooth")  # type: ignore[arg-type]


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_meshes_render_in_float32(dtype: torch.dtype, device: torch.device) -> None:
    mesh = sphere(3, radius=0.7, device=device)
    cams = orbit([15.0], [25.0])
    ref = render_mesh(mesh, cams, 32, 32, position_colour)
    out = render_mesh(mesh.to(dtype=dtype), cams, 32, 32, position_colour)
    assert out.rgb.dtype == torch.float32 and torch.isfinite(out.rgb).all()
    assert (out.opacity - ref.opacity).abs().mean() < 0.02  # the rounded vertices moved slightly


def _perturbed_render(subdivisions: int, seed: int, size: int,
                      device: torch.device) -> tuple[RenderOutput, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    base = sphere(subdivisions, radius=0.7, device=device)
    vertices = (base.vertices + 0.03 * torch.randn(base.vertices.shape, generator=g).to(device)).requires_grad_(True)
    cams = orbit([20.0 + seed, -10.0], [40.0 + 7 * seed, 170.0])
    out = render_mesh(Mesh(vertices, base.faces), cams, size, size, position_colour)
    weights = torch.rand(2, size, size, 4, generator=g).to(device)
    (torch.cat([out.rgb, out.opacity], -1) * weights).sum().backward()
    return out, vertices.grad


def test_compiled_rasteriser_matches_eager_without_breaks_or_recompiles(device: torch.device,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """The rasteriser's and anti-aliasing's pure tensor pieces go through ``compiled_for`` (CUDA).
    Compiled, they must give the eager results for meshes and images of changing sizes, in whole
    graphs (a graph break would fall back to op-by-op launches) compiled once (dynamic shapes). On
    the CPU the graphs are traced and run by ``aot_eager``: inductor's CPU compile costs a minute."""
    import torch._dynamo

    from morpheus_core.runtime import devices

    eager = [_perturbed_render(sub, seed, size, device) for sub, seed, size in ((2, 0, 40), (3, 1, 56))]
    compile_fn = torch.compile
    if device.type == "cpu":
        monkeypatch.setattr(torch, "compile", lambda fn, **kw: compile_fn(fn, backend="aot_eager", **kw))
    monkeypatch.setattr(devices, "compile_enabled", lambda _device: True)
    monkeypatch.setattr(devices, "_compiled", {})
    torch._dynamo.reset()
    torch._dynamo.utils.counters.clear()
    compiled = [_perturbed_render(2, 0, 40, device)]
    graphs = torch._dynamo.utils.counters["stats"]["unique_graphs"]
    compiled.append(_perturbed_render(3, 1, 56, device))
    assert graphs >= 8, "the rasteriser's pieces were not compiled"
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] == graphs, "a new mesh or image size recompiled"
    assert not torch._dynamo.utils.counters["graph_break"], dict(torch._dynamo.utils.counters["graph_break"])
    for (got, got_grad), (want, want_grad) in zip(compiled, eager, strict=True):
        for name in ("rgb", "opacity", "depth", "normal"):
            assert torch.allclose(getattr(got, name), getattr(want, name), atol=1e-5), name
        assert float(want_grad.abs().sum()) > 0
        assert torch.allclose(got_grad, want_grad, rtol=1e-4, atol=1e-5 * float(want_grad.abs().max()))
    torch._dynamo.reset()


def test_a_function_torch_compile_fails_on_runs_eagerly_after_one_warning(monkeypatch: pytest.MonkeyPatch) -> None:
    from torch._dynamo.exc import BackendCompilerFailed

    from morpheus_core.runtime import devices

    def broken_backend(gm: torch.fx.GraphModule, example_inputs: list) -> None:
        raise RuntimeError("backend bug")

    want, want_grad = _perturbed_render(2, 0, 40, torch.device("cpu"))
    compile_fn = torch.compile
    monkeypatch.setattr(torch, "compile", lambda fn, **kw: compile_fn(fn, backend=broken_backend, **kw))
    monkeypatch.setattr(devices, "compile_enabled", lambda _device: True)
    monkeypatch.setattr(devices, "_compiled", {})
    torch._dynamo.reset()
    with pytest.warns(RuntimeWarning, match="runs eagerly from now on") as caught:
        got, got_grad = _perturbed_render(2, 0, 40, torch.device("cpu"))
    assert all(issubclass(w.category, RuntimeWarning) for w in caught)
    assert set(devices._compiled) and all(devices._compiled[fn] is fn for fn in devices._compiled)
    assert torch.equal(got.rgb, want.rgb) and torch.equal(got_grad, want_grad)
    with pytest.raises(BackendCompilerFailed):
        compile_fn(lambda x: x + 1, backend=broken_backend)(torch.ones(2))
    torch._dynamo.reset()
