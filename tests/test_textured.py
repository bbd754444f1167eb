"""Textured meshes: exported GLB / OBJ assets load back and render like the colour field they were baked
from; texture lookups are exact at texel centres and differentiable; surface samples are uniform by
area, lie on the mesh and carry the field's colour; bad files raise typed errors naming the path."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

from morpheus_core.cameras import sample_orbit
from morpheus_core.export.gltf import export_glb, export_obj
from morpheus_core.export.uv_bake import BakeConfig, bake_uv
from morpheus_core.geometry.mesh import Mesh
from morpheus_core.render.mesh_renderer import MeshRenderConfig, render_mesh
from morpheus_core.render.textured import (
    MeshLoadError,
    NoTextureError,
    TexturedMesh,
    load_textured,
    render_textured,
    sample_surface,
    sample_texture,
)
from tests.test_texture import blob, colour_field

# Measured ≈61 dB (8-bit 256² texture, bilinear). Shifting the lookup by half a texel drops it to
# ≈45 dB and flipping v to ≈10 dB, so 50 dB catches orientation and texel-centre mistakes (the
# brief's floor was 28 dB).
MIN_PSNR_DB = 50.0


@pytest.fixture(scope="module")
def source() -> Mesh:
    return blob(3)


@pytest.fixture(scope="module")
def baked(source: Mesh):
    return bake_uv(source, colour_field, BakeConfig(texture_size=256))


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(-10 * torch.log10(((a - b) ** 2).mean()))


@pytest.mark.parametrize("suffix", ["glb", "obj"])
def test_exported_asset_renders_like_its_colour_field(baked, source: Mesh, tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"asset.{suffix}"
    (export_glb if suffix == "glb" else export_obj)(baked, path)
    mesh = load_textured(path)
    n = len(baked.vertices)
    assert mesh.vertices.shape == (n, 3) and mesh.vertices.dtype == torch.float32
    assert mesh.faces.shape == (len(baked.faces), 3) and mesh.faces.dtype == torch.int64
    assert mesh.uvs.shape == (n, 2) and mesh.uvs.dtype == torch.float32
    assert mesh.texture.shape == (256, 256, 3) and mesh.texture.dtype == torch.float32
    assert 0.0 <= float(mesh.texture.min()) and float(mesh.texture.max()) <= 1.0
    # The file holds what the bake produced (OBJ text keeps 7 significant digits).
    in_memory = TexturedMesh.from_baked(baked)
    assert torch.equal(mesh.faces, in_memory.faces) and torch.equal(mesh.texture, in_memory.texture)
    assert torch.allclose(mesh.uvs, in_memory.uvs, atol=1e-6)

    cams = sample_orbit(4, generator=torch.Generator().manual_seed(1))
    ref = render_mesh(source, cams, 96, 96, colour_field)
    out = render_textured(mesh, cams, 96, 96)
    covered = ref.opacity[..., 0] > 0
    assert covered.sum() > 4 * 500
    assert torch.equal(out.opacity > 0, ref.opacity > 0) and torch.equal(out.opacity == 1, ref.opacity == 1)
    # Same geometry: the anti-aliased coverage, depth and normals agree (seam copies are welded).
    assert torch.allclose(out.opacity, ref.opacity, atol=1e-4)
    assert torch.allclose(out.depth, ref.depth, atol=1e-4) and torch.allclose(out.normal, ref.normal, atol=1e-4)
    assert psnr(out.rgb[covered], ref.rgb[covered]) >= MIN_PSNR_DB
    assert torch.equal(out.rgb[~covered], torch.ones_like(out.rgb[~covered]))  # white background
    # Teeth: the same texture read with row 0 at v = 0 renders clearly wrong.
    flipped = TexturedMesh(mesh.vertices, mesh.faces, mesh.uvs, mesh.texture.flip(0))
    assert psnr(render_textured(flipped, cams, 96, 96).rgb[covered], ref.rgb[covered]) < 20


def test_render_options_and_gradients_reach_texture_and_vertices(baked, source: Mesh) -> None:
    cams = sample_orbit(2, generator=torch.Generator().manual_seed(2))
    mesh = TexturedMesh.from_baked(baked)
    config = MeshRenderConfig(normals="face", antialias=False)
    ref = render_mesh(source, cams, 40, 48, colour_field, background=torch.tensor([0.1, 0.2, 0.3]), config=config)
    texture = mesh.texture.clone().requires_grad_(True)
    vertices = mesh.vertices.clone().requires_grad_(True)
    out = render_textured(TexturedMesh(vertices, mesh.faces, mesh.uvs, texture), cams, 40, 48,
                          background=torch.tensor([0.1, 0.2, 0.3]), config=config)
    assert torch.equal(out.opacity, ref.opacity)
    assert torch.allclose(out.normal, ref.normal, atol=1e-5)
    assert torch.allclose(out.rgb[ref.opacity[..., 0] == 0], torch.tensor([0.1, 0.2, 0.3]))
    (out.rgb.sum() + out.opacity.sum()).backward()
    assert texture.grad.abs().sum() > 0 and torch.isfinite(vertices.grad).all()
    # Seam copies of a vertex get the same gradient, so an optimiser keeps them together.
    _, weld = mesh.welded()
    first = torch.zeros(int(weld.max()) + 1, dtype=torch.int64).scatter_(0, weld.flip(0), torch.arange(
        len(weld)).flip(0))
    assert torch.equal(vertices.grad, vertices.grad[first[weld]])
    assert (weld.bincount() > 1).any() and vertices.grad.abs().sum() > 0


def test_sample_texture_is_exact_at_texel_centres_and_bilinear_between() -> None:
    g = torch.Generator().manual_seed(3)
    h, w = 7, 5  # not square: rows and columns must not be mixed up
    texture = torch.rand(h, w, 3, generator=g)
    rows, cols = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    uv = torch.stack([(cols + 0.5) / w, 1 - (rows + 0.5) / h], -1).reshape(-1, 2)
    assert torch.allclose(sample_texture(texture, uv), texture.reshape(-1, 3), atol=1e-6)

    uv = torch.rand(500, 2, generator=g) * 1.4 - 0.2  # some outside [0, 1]: clamp to the edge
    x = (uv[:, 0] * w - 0.5).clamp(0, w - 1)
    y = ((1 - uv[:, 1]) * h - 0.5).clamp(0, h - 1)
    x0, y0 = x.floor().long().clamp(max=w - 2), y.floor().long().clamp(max=h - 2)
    fx, fy = (x - x0).unsqueeze(-1), (y - y0).unsqueeze(-1)
    expected = (texture[y0, x0] * (1 - fx) * (1 - fy) + texture[y0, x0 + 1] * fx * (1 - fy)
                + texture[y0 + 1, x0] * (1 - fx) * fy + texture[y0 + 1, x0 + 1] * fx * fy)
    assert torch.allclose(sample_texture(texture, uv), expected, atol=1e-5)


def test_sample_texture_gradients() -> None:
    g = torch.Generator().manual_seed(4)
    texture = torch.rand(3, 4, 3, generator=g, dtype=torch.float64).requires_grad_(True)
    uv = (0.05 + 0.9 * torch.rand(6, 2, generator=g, dtype=torch.float64)).requires_grad_(True)
    assert torch.autograd.gradcheck(sample_texture, (texture, uv))


def _on_surface_distance(points: torch.Tensor, vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Per point, the smallest plane distance over the faces whose triangle contains the point's
    projection (barycentrics ≥ −1e-5); +inf if none does."""
    a, b, c = (vertices[faces[:, k]].double() for k in range(3))
    n = torch.linalg.cross(b - a, c - a, dim=-1)
    best = []
    for chunk in points.double().split(256):
        d = chunk[:, None] - a[None]  # (P, F, 3)
        plane = (d * n).sum(-1) / n.norm(dim=-1)
        area = (n * n).sum(-1)
        beta = (torch.linalg.cross(d, (c - a).expand_as(d), dim=-1) * n).sum(-1) / area
        gamma = (torch.linalg.cross((b - a).expand_as(d), d, dim=-1) * n).sum(-1) / area
        inside = (beta >= -1e-5) & (gamma >= -1e-5) & (beta + gamma <= 1 + 1e-5)
        best.append(torch.where(inside, plane.abs(), torch.inf).amin(-1))
    return torch.cat(best)


def test_surface_samples_lie_on_the_mesh_and_carry_the_baked_colours(baked) -> None:
    mesh = TexturedMesh.from_baked(baked)
    points, colours = sample_surface(mesh, 20_000, torch.Generator().manual_seed(5))
    assert points.shape == (20_000, 3) and colours.shape == (20_000, 3)
    again, _ = sample_surface(mesh, 20_000, torch.Generator().manual_seed(5))
    assert torch.equal(points, again)
    assert float(_on_surface_distance(points[:1000], mesh.vertices, mesh.faces).max()) < 1e-5
    # Tolerance: the bake's 4/255 budget (8-bit rounding, seam dilation; tests/test_texture.py) plus
    # 2/255 for bilinear interpolation of the smooth field on a 256² texture; measured max ≈2.7/255.
    error = (colours - colour_field(points)).abs()
    assert float(error.max()) <= 6 / 255 and float(error.mean()) <= 1 / 255


def test_surface_samples_are_area_weighted_and_uniform_in_each_triangle() -> None:
    # Areas 1 and 3: a right triangle with legs 2 and 1, and one with legs 2 and 3 to its right.
    vertices = torch.tensor([[0, 0, 0], [2, 0, 0], [0, 1, 0], [3, 0, 0], [5, 0, 0], [3, 3, 0]], dtype=torch.float32)
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]])
    g = torch.Generator().manual_seed(6)
    mesh = TexturedMesh(vertices, faces, torch.rand(6, 2, generator=g), torch.rand(4, 4, 3, generator=g))
    points, _ = sample_surface(mesh, 20_000, g)
    first = points[:, 0] < 2.5
    assert abs(float(first.float().mean()) - 0.25) <= 0.02
    # Uniform inside a triangle: the corner sub-triangle x/2 + y < ½ holds a quarter of its area
    # (without the square root, half of the samples would land there).
    p = points[first]
    assert abs(float((p[:, 0] / 2 + p[:, 1] < 0.5).float().mean()) - 0.25) <= 0.02


def test_textured_mesh_checks_its_fields() -> None:
    g = torch.Generator().manual_seed(7)
    vertices, faces = torch.rand(4, 3, generator=g), torch.tensor([[0, 1, 2], [0, 2, 3]])
    uvs, texture = torch.rand(4, 2, generator=g), torch.rand(8, 8, 3, generator=g)
    mesh = TexturedMesh(vertices, faces, uvs, texture).to("cpu")
    assert torch.equal(mesh.mesh.vertices, vertices) and mesh.mesh.num_faces == 2
    with pytest.raises(ValueError, match=r"uvs must be \(4, 2\)"):
        TexturedMesh(vertices, faces, uvs[:3], texture)
    with pytest.raises(ValueError, match="texture must be"):
        TexturedMesh(vertices, faces, uvs, texture[..., :2])
    with pytest.raises(TypeError, match="floating point"):
        TexturedMesh(vertices, faces, uvs, (texture * 255).to(torch.uint8))


def test_missing_file_is_a_load_error_naming_the_path(tmp_path: Path) -> None:
    path = tmp_path / "nowhere" / "asset.glb"
    with pytest.raises(MeshLoadError, match=re.escape(f"{path}: no such file")) as info:
        load_textured(path)
    assert "UVs" in str(info.value) and not isinstance(info.value, NoTextureError)
    with pytest.raises(MeshLoadError, match="is not a file"):
        load_textured(tmp_path)


def test_vertex_colours_without_texture_raise_no_texture_error(tmp_path: Path) -> None:
    box = trimesh.creation.box()
    box.visual.vertex_colors = np.random.default_rng(8).integers(0, 256, (len(box.vertices), 4), dtype=np.uint8)
    path = tmp_path / "coloured.glb"
    box.export(path)
    with pytest.raises(NoTextureError, match=r"coloured\.glb: mesh 0 has vertex/face colours"):
        load_textured(path)


def test_several_textures_raise_no_texture_error(tmp_path: Path) -> None:
    rng = np.random.default_rng(9)
    scene = trimesh.Scene()
    for k in range(2):
        box = trimesh.creation.box()
        image = Image.fromarray(rng.integers(0, 256, (8, 8, 3), dtype=np.uint8))
        box.visual = trimesh.visual.TextureVisuals(uv=rng.random((len(box.vertices), 2)), image=image)
        shift = trimesh.transformations.translation_matrix([3 * k, 0, 0])
        scene.add_geometry(box, node_name=f"box{k}", transform=shift)
    path = tmp_path / "two.glb"
    scene.export(path)
    with pytest.raises(NoTextureError, match="single-texture"):
        load_textured(path)


def test_garbage_and_faceless_files_are_load_errors(tmp_path: Path) -> None:
    garbage = tmp_path / "garbage.glb"
    garbage.write_bytes(np.random.default_rng(8).integers(0, 256, 600, dtype=np.uint8).tobytes())
    with pytest.raises(MeshLoadError, match=r"garbage\.glb: could not be read"):
        load_textured(garbage)
    points_only = tmp_path / "points.obj"
    points_only.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(MeshLoadError, match=r"points\.obj: contains no triangle mesh with faces") as info:
        load_textured(points_only)
    assert not isinstance(info.value, NoTextureError)
