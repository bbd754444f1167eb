"""Texture field, UV bake and export: baked colours survive GLB and OBJ round trips (read back by
trimesh and, for GLB, straight from the glTF buffers), dilation, the face budget, atomic writes."""

from __future__ import annotations

import io
import json
import struct
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

from morpheus_core.export.gltf import encode_glb, export_glb, export_obj
from morpheus_core.export.uv_bake import (
    BakeConfig,
    EmptyMeshError,
    TooManyFacesError,
    bake_uv,
    cluster_decimate,
    dilate,
)
from morpheus_core.geometry.hashgrid import HashGridConfig
from morpheus_core.geometry.mesh import Mesh
from morpheus_core.runtime.atomic_io import atomic_write
from morpheus_core.texture import TextureField, TextureFieldConfig

TOLERANCE = 4.0 / 255.0


def colour_field(points: torch.Tensor) -> torch.Tensor:
    """A smooth analytic albedo in [0.1, 0.9] that differs per channel and along every axis."""
    p = points.double()
    phase = torch.tensor([0.0, 1.3, 2.6], dtype=p.dtype, device=p.device)
    mix = torch.stack([p[:, 0] + 0.5 * p[:, 1], p[:, 1] - 0.7 * p[:, 2], p[:, 2] + 0.4 * p[:, 0]], -1)
    return (0.5 + 0.4 * torch.sin(2.5 * mix + phase)).to(points.dtype)


def blob(subdivisions: int = 3, device: torch.device | str = "cpu") -> Mesh:
    """A lumpy, non-convex closed surface (so the unwrap has several charts and seams)."""
    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    v = torch.tensor(ico.vertices, dtype=torch.float32)
    radius = 0.7 + 0.15 * torch.sin(3 * v[:, 0]) * torch.cos(2 * v[:, 1]) + 0.1 * v[:, 2] ** 2
    return Mesh((v * radius[:, None]).to(device), torch.tensor(ico.faces, dtype=torch.int64, device=device))


def sample_surface(vertices: np.ndarray, faces: np.ndarray, uvs: np.ndarray, count: int, seed: int):
    rng = np.random.default_rng(seed)
    face = rng.integers(0, len(faces), count)
    bary = rng.dirichlet(np.ones(3), count)
    points = (vertices[faces[face]] * bary[..., None]).sum(1)
    uv = (uvs[faces[face]] * bary[..., None]).sum(1)
    return points, uv


def bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Sample an (H, W, C) image at continuous texel coordinates (texel centres at integers), clamped."""
    h, w = image.shape[:2]
    x, y = np.clip(x, 0, w - 1), np.clip(y, 0, h - 1)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    img = image.astype(np.float64) / 255.0
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bottom = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def sample_v_up(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """trimesh / OBJ convention: v = 1 is the top row."""
    h, w = image.shape[:2]
    return bilinear(image, uv[:, 0] * w - 0.5, (1 - uv[:, 1]) * h - 0.5)


def surface_errors(mesh: trimesh.Trimesh, seed: int = 0) -> np.ndarray:
    """Absolute colour errors at 20k random surface points, sampling the re-loaded mesh's own
    texture bilinearly at its own UVs."""
    image = np.asarray(mesh.visual.material.baseColorTexture.convert("RGB")) \
        if hasattr(mesh.visual.material, "baseColorTexture") else np.asarray(mesh.visual.material.image.convert("RGB"))
    points, uv = sample_surface(np.asarray(mesh.vertices), np.asarray(mesh.faces), np.asarray(mesh.visual.uv),
                                20000, seed)
    expected = colour_field(torch.from_numpy(points)).numpy()
    return np.abs(sample_v_up(image, uv) - expected)


def surface_error(mesh: trimesh.Trimesh, seed: int = 0) -> float:
    return float(surface_errors(mesh, seed).mean())


@pytest.fixture(scope="module")
def baked():
    return bake_uv(blob(3), colour_field, BakeConfig(texture_size=512))


def test_bake_covers_the_atlas_and_fills_every_texel(baked) -> None:
    assert baked.texture.shape == (512, 512, 3) and baked.texture.dtype == np.uint8
    assert 0.3 < baked.coverage < 0.95
    assert baked.faces.shape == (1280, 3) and baked.source_faces == 1280
    assert len(baked.vertices) > 642  # split along seams
    assert (baked.uvs >= 0).all() and (baked.uvs <= 1).all()
    # Dilation and the final mean fill leave no texel at the black of an empty raster.
    assert baked.texture.min() >= int(0.1 * 255) - 1
    np.testing.assert_allclose(np.linalg.norm(baked.normals, axis=1), 1.0, atol=1e-5)


def test_glb_round_trip_reproduces_the_colour_field(baked, tmp_path: Path) -> None:
    path = export_glb(baked, tmp_path / "asset.glb")
    loaded = trimesh.load(path, force="mesh", process=False)
    assert len(loaded.faces) == len(baked.faces)
    assert loaded.visual.material.metallicFactor == 0.0
    errors = surface_errors(loaded)
    assert errors.mean() <= TOLERANCE
    assert errors.max() <= 2 * TOLERANCE  # also at points on and near the UV seams


def test_glb_texture_coordinates_follow_gltf_top_left_origin(baked) -> None:
    """Read the GLB's buffers directly (no trimesh loader): with glTF's convention (v = 0 is the
    first image row) the texture must reproduce the field — so other viewers see what we baked."""
    data = encode_glb(baked)
    magic, _, _ = struct.unpack("<4sII", data[:12])
    assert magic == b"glTF"
    json_len = struct.unpack("<I", data[12:16])[0]
    doc = json.loads(data[20: 20 + json_len])
    binary = data[20 + json_len + 8:]

    def view(index: int) -> bytes:
        bv = doc["bufferViews"][index]
        return binary[bv.get("byteOffset", 0): bv.get("byteOffset", 0) + bv["byteLength"]]

    def accessor(index: int, dtype, width: int) -> np.ndarray:
        acc = doc["accessors"][index]
        raw = view(acc["bufferView"])[acc.get("byteOffset", 0):]
        return np.frombuffer(raw, dtype=dtype, count=acc["count"] * width).reshape(acc["count"], width)

    prim = doc["meshes"][0]["primitives"][0]
    positions = accessor(prim["attributes"]["POSITION"], np.float32, 3).astype(np.float64)
    uvs = accessor(prim["attributes"]["TEXCOORD_0"], np.float32, 2).astype(np.float64)
    index_type = {5125: np.uint32, 5123: np.uint16}[doc["accessors"][prim["indices"]]["componentType"]]
    faces = accessor(prim["indices"], index_type, 1).reshape(-1, 3).astype(np.int64)
    material = doc["materials"][prim["material"]]
    texture = doc["textures"][material["pbrMetallicRoughness"]["baseColorTexture"]["index"]]
    image = np.asarray(Image.open(io.BytesIO(view(doc["images"][texture["source"]]["bufferView"]))).convert("RGB"))
    points, uv = sample_surface(positions, faces, uvs, 20000, seed=1)
    h, w = image.shape[:2]
    got = bilinear(image, uv[:, 0] * w - 0.5, uv[:, 1] * h - 0.5)  # glTF: v = 0 is the top row
    expected = colour_field(torch.from_numpy(points)).numpy()
    assert np.abs(got - expected).mean() <= TOLERANCE
    # And the flipped reading is clearly wrong, so the check has teeth.
    flipped = bilinear(image, uv[:, 0] * w - 0.5, (1 - uv[:, 1]) * h - 0.5)
    assert np.abs(flipped - expected).mean() > 5 * TOLERANCE


def test_obj_round_trip(baked, tmp_path: Path) -> None:
    path = export_obj(baked, tmp_path / "asset.obj")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["asset.mtl", "asset.obj", "asset.png"]
    assert "Kd 1 1 1" in (tmp_path / "asset.mtl").read_text()
    loaded = trimesh.load(path, force="mesh", process=False, maintain_order=True)
    assert len(loaded.faces) == len(baked.faces)
    assert surface_error(loaded, seed=2) <= TOLERANCE


def test_failed_export_leaves_old_file_and_no_temporary(baked, tmp_path: Path, monkeypatch) -> None:
    target = tmp_path / "asset.glb"
    export_glb(baked, target)
    good = target.read_bytes()

    def broken(_baked) -> bytes:
        raise RuntimeError("encoder crashed")

    monkeypatch.setattr("morpheus_core.export.gltf.encode_glb", broken)
    with pytest.raises(RuntimeError, match="encoder crashed"):
        export_glb(baked, target)
    assert target.read_bytes() == good
    assert [p.name for p in tmp_path.iterdir()] == ["asset.glb"]

    def half_then_fail(tmp) -> None:
        tmp.write_bytes(good[: len(good) // 2])
        raise OSError("disk full")

    fresh = tmp_path / "new.glb"
    with pytest.raises(OSError, match="disk full"):
        atomic_write(fresh, half_then_fail)
    assert not fresh.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["asset.glb"]


def test_dilation_grows_colours_outward() -> None:
    g = torch.Generator().manual_seed(0)
    image = torch.rand(9, 9, 3, generator=g)
    mask = torch.zeros(9, 9, dtype=torch.bool)
    mask[4, 4] = True
    out, grown = dilate(image, mask, iterations=2)
    assert grown[2:7, 2:7].all() and grown.sum() == 25
    assert torch.allclose(out[2:7, 2:7], image[4, 4].expand(5, 5, 3))
    assert torch.allclose(out[0, 0], image[4, 4])  # never reached: filled with the mean colour
    two = torch.zeros(1, 4, dtype=torch.bool)
    two[0, 0] = two[0, 3] = True
    img = torch.tensor([[[0.0], [9.0], [9.0], [1.0]]])
    out, _ = dilate(img, two, iterations=1)
    assert torch.allclose(out[0, :, 0], torch.tensor([0.0, 0.0, 1.0, 1.0]))


def test_face_budget_raises_or_decimates() -> None:
    mesh = blob(3)  # 1280 faces
    with pytest.raises(TooManyFacesError, match="DMTet grid resolution of about"):
        bake_uv(mesh, colour_field, BakeConfig(texture_size=64, max_faces=500, on_too_many_faces="raise"))
    with pytest.warns(UserWarning, match="decimating"):
        baked = bake_uv(mesh, colour_field, BakeConfig(texture_size=256, max_faces=500))
    assert 250 < len(baked.faces) <= 500 and baked.source_faces == 1280
    reloaded = trimesh.load(io.BytesIO(encode_glb(baked)), file_type="glb", force="mesh", process=False)
    assert surface_error(reloaded, seed=3) <= 2 * TOLERANCE  # coarser texture, same field


def test_cluster_decimate_keeps_the_shape() -> None:
    mesh = blob(4)
    small = cluster_decimate(mesh, 1000)
    assert 500 < small.num_faces <= 1000
    radius = mesh.vertices.norm(dim=-1)
    small_radius = small.vertices.norm(dim=-1)
    assert small_radius.min() > radius.min() - 0.1 and small_radius.max() < radius.max() + 0.01
    assert small.faces.min() >= 0 and small.faces.max() < small.num_vertices


def test_empty_mesh_is_a_typed_error() -> None:
    empty = Mesh(torch.zeros(0, 3), torch.zeros(0, 3, dtype=torch.int64))
    with pytest.raises(EmptyMeshError):
        bake_uv(empty, colour_field)


SMALL_GRID = HashGridConfig(n_levels=4, log2_table_size=12, base_resolution=4, per_level_scale=2.0)


def test_texture_field_range_gradients_and_fit(device: torch.device) -> None:
    config = TextureFieldConfig(hashgrid=SMALL_GRID, bound=1.0, hidden_dim=32)
    field_a = TextureField(config, generator=torch.Generator().manual_seed(0)).to(device)
    field_b = TextureField(config, generator=torch.Generator().manual_seed(0)).to(device)
    g = torch.Generator().manual_seed(1)
    points = (torch.rand(4096, 3, generator=g) * 2.4 - 1.2).to(device)  # some outside the box: clamped
    out = field_a(points)
    assert out.shape == (4096, 3) and ((out > 0) & (out < 1)).all()
    assert torch.equal(out, field_b(points))  # seeded initialisation is reproducible
    assert field_a(points.reshape(64, 64, 3)).shape == (64, 64, 3)
    p = points[:16].clone().requires_grad_(True)
    field_a(p).sum().backward()
    assert torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0
    # A few Adam steps fit the analytic field far better than the initial guess.
    opt = torch.optim.Adam(field_a.parameters(), lr=2e-2)
    inside = points[:1024].clamp(-1, 1)
    target = colour_field(inside)
    first = None
    for _ in range(60):
        loss = ((field_a(inside) - target) ** 2).mean()
        first = first if first is not None else loss.item()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert loss.item() < 0.2 * first
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        field_a(points[:, :2])


def test_bake_a_texture_field_on_device(device: torch.device) -> None:
    field = TextureField(TextureFieldConfig(hashgrid=SMALL_GRID), generator=torch.Generator().manual_seed(3))
    mesh = blob(2, device=device)
    baked = bake_uv(mesh, field.to(device), BakeConfig(texture_size=128))
    loaded = trimesh.load(io.BytesIO(encode_glb(baked)), file_type="glb", force="mesh", process=False)
    image = np.asarray(loaded.visual.material.baseColorTexture.convert("RGB"))
    points, uv = sample_surface(np.asarray(loaded.vertices), np.asarray(loaded.faces), np.asarray(loaded.visual.uv),
                                5000, seed=4)
    with torch.no_grad():
        expected = field(torch.from_numpy(points).float().to(device)).cpu().double().numpy()
    assert np.abs(sample_v_up(image, uv) - expected).mean() <= TOLERANCE
