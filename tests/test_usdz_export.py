"""USDZ export (morpheus_core.export.usdz): compliance, round trip, package layout, texture orientation, failures."""

from __future__ import annotations

import dataclasses
import io
import struct
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

pxr = pytest.importorskip("pxr", reason="usd-core is a declared dependency")
from pxr import Sdf, Usd, UsdGeom, UsdShade  # noqa: E402

from morpheus_core.export import usdz  # noqa: E402
from morpheus_core.geometry.textured_mesh import BakedTexture  # noqa: E402


def _icosphere_soup(rng: np.random.Generator, size: tuple[int, int] = (32, 32)) -> BakedTexture:
    """An icosahedron subdivided once (80 triangles), every triangle with its own three vertices (as if
    each were a UV chart), random UVs in [0, 1], unit normals, and a random texture."""
    t = (1 + 5**0.5) / 2
    verts = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                      [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)
    faces = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
             [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11],
             [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    tris = []
    for a, b, c in faces:  # split each triangle into four at its edge midpoints
        pa, pb, pc = verts[a], verts[b], verts[c]
        ab, bc, ca = (pa + pb) / 2, (pb + pc) / 2, (pc + pa) / 2
        tris += [(pa, ab, ca), (ab, pb, bc), (ca, bc, pc), (ab, bc, ca)]
    corners = np.array(tris).reshape(-1, 3)
    normals = corners / np.linalg.norm(corners, axis=1, keepdims=True)
    return BakedTexture(
        vertices=0.15 * normals + rng.normal(0, 1e-3, normals.shape),  # ~30 cm across, in metres
        faces=np.arange(len(corners)).reshape(-1, 3),
        uvs=rng.uniform(0, 1, (len(corners), 2)),
        normals=normals,
        texture=rng.integers(0, 256, (*size, 3), dtype=np.uint8),
        coverage=1.0,
        source_faces=len(tris),
    )


@pytest.fixture(scope="module")
def baked() -> BakedTexture:
    return _icosphere_soup(np.random.default_rng(20240611))


@pytest.fixture(scope="module")
def package(baked: BakedTexture, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return usdz.export_usdz(baked, tmp_path_factory.mktemp("usdz") / "chair.usdz", name="3d chair!")


def _data_offsets(data: bytes) -> dict[str, int]:
    """Where each entry's data starts: after its 30-byte local header, name and extra field."""
    offsets = {}
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        for info in zf.infolist():
            name_len, extra_len = struct.unpack_from("<HH", data, info.header_offset + 26)
            offsets[info.filename] = info.header_offset + 30 + name_len + extra_len
    return offsets


def test_compliance_checker_reports_no_errors(package: Path) -> None:
    check = usdz.check_usdz(package)
    assert check.checker  # which of USD's checkers ran depends on the usd-core version
    assert check.errors == [], check.errors
    assert check.warnings == [], check.warnings
    assert check.ok


def test_compliance_checker_catches_a_compressed_texture(package: Path, tmp_path: Path) -> None:
    """Not vacuous: a deflated texture (root layer still stored, so USD can open it) fails the checks."""
    bad = tmp_path / "deflated.usdz"
    with zipfile.ZipFile(package) as src, zipfile.ZipFile(bad, "w") as dst:
        for name in src.namelist():
            kind = zipfile.ZIP_DEFLATED if name.endswith(".png") else zipfile.ZIP_STORED
            dst.writestr(name, src.read(name), compress_type=kind)
    check = usdz.check_usdz(bad)
    assert not check.ok
    assert any("compression" in e.lower() for e in check.errors), check.errors


def test_round_trip_through_usd(baked: BakedTexture, package: Path) -> None:
    stage = Usd.Stage.Open(str(package))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    root = stage.GetDefaultPrim()
    assert root and root.GetName() == "_d_chair_" and root.IsA(UsdGeom.Xform)

    meshes = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    assert len(meshes) == 1 and meshes[0].GetPath().HasPrefix(root.GetPath())
    mesh = UsdGeom.Mesh(meshes[0])
    points = np.array(mesh.GetPointsAttr().Get())
    np.testing.assert_allclose(points, baked.vertices, rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(np.array(mesh.GetFaceVertexCountsAttr().Get()), 3)
    np.testing.assert_array_equal(np.array(mesh.GetFaceVertexIndicesAttr().Get()), baked.faces.reshape(-1))
    np.testing.assert_allclose(np.array(mesh.GetNormalsAttr().Get()), baked.normals, rtol=1e-6, atol=1e-7)
    assert mesh.GetNormalsInterpolation() == UsdGeom.Tokens.vertex
    st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
    assert st.GetTypeName() == Sdf.ValueTypeNames.TexCoord2fArray
    assert st.GetInterpolation() == UsdGeom.Tokens.vertex
    np.testing.assert_allclose(np.array(st.Get()), baked.uvs, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(np.array(mesh.GetExtentAttr().Get()), [points.min(0), points.max(0)])
    assert mesh.GetSubdivisionSchemeAttr().Get() == UsdGeom.Tokens.none
    assert mesh.GetDoubleSidedAttr().Get() is False

    material, _ = UsdShade.MaterialBindingAPI(mesh.GetPrim()).ComputeBoundMaterial()
    assert material and material.GetPath().HasPrefix(root.GetPath())
    surface = material.ComputeSurfaceSource()[0]
    assert surface.GetShaderId() == "UsdPreviewSurface"
    assert surface.GetInput("metallic").Get() == 0.0 and surface.GetInput("roughness").Get() == 1.0
    texture = UsdShade.Shader(surface.GetInput("diffuseColor").GetConnectedSource()[0].GetPrim())
    assert texture.GetShaderId() == "UsdUVTexture"
    assert texture.GetInput("file").Get().path == usdz.TEXTURE_NAME
    assert texture.GetInput("file").Get().resolvedPath.startswith(str(package))  # resolved inside the package
    reader = UsdShade.Shader(texture.GetInput("st").GetConnectedSource()[0].GetPrim())
    assert reader.GetShaderId() == "UsdPrimvarReader_float2" and reader.GetInput("varname").Get() == "st"


def test_package_layout_is_usdz(baked: BakedTexture, package: Path) -> None:
    data = package.read_bytes()
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        infos = zf.infolist()
        assert [i.filename for i in infos] == ["_d_chair_.usdc", usdz.TEXTURE_NAME]  # root layer first
        assert all(i.compress_type == zipfile.ZIP_STORED for i in infos)
        assert zf.read(infos[0]).startswith(b"PXR-USDC")  # binary crate, not usda
        png = zf.read(usdz.TEXTURE_NAME)
    assert all(off % 64 == 0 for off in _data_offsets(data).values()), _data_offsets(data)
    decoded = np.asarray(Image.open(io.BytesIO(png)))
    assert decoded.dtype == np.uint8
    np.testing.assert_array_equal(decoded, baked.texture)


def test_texture_orientation_through_st(tmp_path: Path) -> None:
    """Each vertex sits at a texel centre; looking that texel up from the *package* the USD way (st origin at
    the image's bottom-left) gives the colour the BakedTexture convention (row 0 at v = 1) promises.
    A non-square texture also catches swapped axes."""
    rng = np.random.default_rng(7)
    h, w = 24, 40
    base = _icosphere_soup(rng, size=(h, w))
    rows = rng.integers(0, h, len(base.vertices))
    cols = rng.integers(0, w, len(base.vertices))
    uvs = np.stack([(cols + 0.5) / w, 1 - (rows + 0.5) / h], axis=1)  # row 0 at v = 1
    baked = dataclasses.replace(base, uvs=uvs)
    expected = baked.texture[rows, cols]

    path = usdz.export_usdz(baked, tmp_path / "orient.usdz")
    stage = Usd.Stage.Open(str(path))
    mesh = next(p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
    st = np.array(UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st").Get(), dtype=np.float64)
    with zipfile.ZipFile(path) as zf:
        image = np.asarray(Image.open(io.BytesIO(zf.read(usdz.TEXTURE_NAME))))
    col = np.floor(st[:, 0] * w).astype(int)
    row_from_bottom = np.floor(st[:, 1] * h).astype(int)
    np.testing.assert_array_equal(image[h - 1 - row_from_bottom, col], expected)
    # The check can fail: reading with a top-left origin (the glTF way) gives other colours.
    assert not np.array_equal(image[row_from_bottom, col], expected)


def test_prim_name_is_sanitised(baked: BakedTexture) -> None:
    for name, prim in (("", "asset"), ("chair_01", "chair_01"), ("my chair.v2", "my_chair_v2")):
        with zipfile.ZipFile(io.BytesIO(usdz.encode_usdz(baked, name))) as zf:
            assert zf.namelist()[0] == f"{prim}.usdc"


def _broken(baked: BakedTexture, what: str) -> BakedTexture:
    if what == "nan vertex":
        vertices = baked.vertices.copy()
        vertices[5, 1] = np.nan
        return dataclasses.replace(baked, vertices=vertices)
    if what == "inf normal":
        normals = baked.normals.copy()
        normals[0, 2] = np.inf
        return dataclasses.replace(baked, normals=normals)
    if what == "face out of range":
        faces = baked.faces.copy()
        faces[3, 2] = len(baked.vertices)
        return dataclasses.replace(baked, faces=faces)
    if what == "negative face":
        faces = baked.faces.copy()
        faces[0, 0] = -1
        return dataclasses.replace(baked, faces=faces)
    if what == "empty mesh":
        return dataclasses.replace(baked, faces=np.zeros((0, 3), np.int64))
    if what == "float texture":
        return dataclasses.replace(baked, texture=baked.texture.astype(np.float32) / 255)
    if what == "rgba texture":
        return dataclasses.replace(baked, texture=np.zeros((8, 8, 4), np.uint8))
    if what == "uv count":
        return dataclasses.replace(baked, uvs=baked.uvs[:-1])
    raise AssertionError(what)


BROKEN = ["nan vertex", "inf normal", "face out of range", "negative face", "empty mesh", "float texture",
          "rgba texture", "uv count"]


@pytest.mark.parametrize("what", BROKEN)
def test_bad_input_raises_before_writing(baked: BakedTexture, tmp_path: Path, what: str) -> None:
    target = tmp_path / "out.usdz"
    with pytest.raises(ValueError):
        usdz.export_usdz(_broken(baked, what), target)
    assert list(tmp_path.iterdir()) == []  # no file, no temporary left behind


def test_failed_write_leaves_the_old_file(baked: BakedTexture, tmp_path: Path, monkeypatch) -> None:
    target = usdz.export_usdz(baked, tmp_path / "out.usdz")
    good = target.read_bytes()
    with pytest.raises(ValueError, match="face indices"):
        usdz.export_usdz(_broken(baked, "face out of range"), target)

    def fail(*args, **kwargs):  # USD failing half-way through authoring
        raise RuntimeError("disk full")

    monkeypatch.setattr(usdz, "_author_stage", fail)
    with pytest.raises(RuntimeError, match="disk full"):
        usdz.export_usdz(baked, target)
    assert target.read_bytes() == good
    assert [p.name for p in tmp_path.iterdir()] == ["out.usdz"]
    assert usdz.check_usdz(target).ok


def test_missing_usd_says_how_to_install(baked: BakedTexture, monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "pxr", None)  # makes `from pxr import ...` raise ImportError
    with pytest.raises(ImportError, match="pip install usd-core"):
        usdz.encode_usdz(baked)


def test_the_same_asset_gives_the_same_bytes(baked: BakedTexture) -> None:
    first = usdz.encode_usdz(baked)
    entries = zipfile.ZipFile(io.BytesIO(first)).infolist()
    assert {info.date_time[0] for info in entries} == {1980}  # fixed stamps, not the clock's
    assert usdz.encode_usdz(baked) == first
