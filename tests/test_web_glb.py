"""The web GLB (``morpheus_core.export.web_glb``): it decodes back to the input, meets its byte budget, and
loads where it is meant to (meshoptimizer's JS decoder; model-viewer in a browser: tests/test_export_stage.py).

Inputs are fresh random meshes each run (the seed is printed, so a failure can be replayed with
``WEB_GLB_SEED``): a deformed sphere cut into 2–4 UV charts (vertices split at the cuts) of a few
hundred triangles, with a 256–1024 px texture of smooth noise crossed by a few sharp lines.

The GLB is parsed here, independently of the writer: chunks, accessors, dequantization by the
glTF rules (uint16 normalized = q / 65535, int8 normalized = max(q / 127, −1), then the node's
translation and scale), meshopt streams decoded with the ``meshoptimizer`` Python binding.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import struct
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image, ImageDraw
from scipy.spatial import cKDTree

from morpheus_core.export.glb_geometry import EXT_MESHOPT, EXT_QUANTIZATION, meshopt_available
from morpheus_core.export.web_glb import EXT_WEBP, SizeBudgetError, encode_web_glb, write_web_glb
from morpheus_core.geometry.textured_mesh import BakedTexture

REPO = Path(__file__).resolve().parents[1]
WEB_TOOLS = REPO / "tools" / "web" / "node_modules"
MESHOPT_JS = WEB_TOOLS / "meshoptimizer" / "meshopt_decoder.mjs"
NODE = shutil.which(os.environ.get("MORPHEUS_NODE", "node"))

PSNR_FLOOR_DB = 28.0
"""WebP at quality 90 (the first rung) against the input texture. Measured on 20 seeds of these
textures: 31.7 dB at worst, 36.9 dB mean; the sharp saturated lines cost most (WebP halves chroma)."""

needs_meshopt = pytest.mark.skipif(meshopt_available() is not None, reason=str(meshopt_available()))


# ----------------------------------------------------------------------------------------- inputs


@pytest.fixture
def rng() -> np.random.Generator:
    seed = int(os.environ.get("WEB_GLB_SEED", np.random.SeedSequence().entropy % 2**63))
    print(f"WEB_GLB_SEED={seed}")  # shown by pytest when the test fails
    return np.random.default_rng(seed)


def random_texture(rng: np.random.Generator, size: int | None = None) -> np.ndarray:
    """Smooth colour noise (bicubic from a coarse grid: compresses like a real bake) and a few sharp lines."""
    size = int(rng.integers(256, 1025)) if size is None else size
    coarse = int(rng.integers(4, 13))
    base = Image.fromarray(rng.integers(0, 256, (coarse, coarse, 3), dtype=np.uint8)).resize((size, size),
                                                                                             Image.BICUBIC)
    draw = ImageDraw.Draw(base)
    for _ in range(int(rng.integers(3, 7))):
        ends = [tuple(int(c) for c in rng.integers(0, size, 2)) for _ in range(2)]
        draw.line(ends, fill=tuple(int(c) for c in rng.integers(0, 256, 3)), width=int(rng.integers(1, 4)))
    return np.asarray(base).copy()


def random_baked(rng: np.random.Generator, texture_size: int | None = None, grid: tuple[int, int] | None = None,
                 ) -> BakedTexture:
    """A deformed sphere band cut into 2–4 UV charts; vertices on a cut are duplicated (one per chart)."""
    nu, nv = grid if grid is not None else (int(rng.integers(12, 19)), int(rng.integers(8, 13)))
    charts = int(rng.integers(2, 5))
    cuts = np.linspace(0, nu - 1, charts + 1).round().astype(int)
    theta = np.linspace(0.0, 2 * np.pi, nu)
    phi = np.linspace(0.15 * np.pi, 0.85 * np.pi, nv)
    radius = 1.0 + 0.15 * rng.standard_normal((nu, nv))
    radius[-1] = radius[0]  # the sphere closes at theta = 2π
    verts, normals, uvs, faces = [], [], [], []
    for c in range(charts):
        cols = np.arange(cuts[c], cuts[c + 1] + 1)
        first = len(verts)
        for i in cols:
            for j in range(nv):
                d = np.array([np.sin(phi[j]) * np.cos(theta[i]), np.sin(phi[j]) * np.sin(theta[i]), np.cos(phi[j])])
                verts.append(d * radius[i, j])
                normals.append(d + 0.05 * rng.standard_normal(3))
                # Each chart gets its own column of the atlas, with a gap.
                u = (c + 0.05 + 0.9 * (i - cols[0]) / (cols[-1] - cols[0])) / charts
                uvs.append([u, 0.02 + 0.96 * j / (nv - 1)])
        for a in range(len(cols) - 1):
            for j in range(nv - 1):
                p, q = first + a * nv + j, first + (a + 1) * nv + j
                faces += [[p, q, q + 1], [p, q + 1, p + 1]]
    scale = float(rng.uniform(0.05, 5.0))
    offset = rng.uniform(-10.0, 10.0, 3)
    return BakedTexture(vertices=np.array(verts) * scale + offset, faces=np.array(faces, dtype=np.int64),
                        uvs=np.array(uvs), normals=np.array(normals), texture=random_texture(rng, texture_size),
                        coverage=1.0, source_faces=len(faces))


# ------------------------------------------------------------------------------------ GLB reading


def read_glb(data: bytes) -> dict[str, Any]:
    """Parse a GLB: world-space positions, unit normals, v-up UVs, faces, the image bytes and the JSON."""
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    assert (magic, version, length) == (b"glTF", 2, len(data))
    json_len, json_type = struct.unpack_from("<II", data, 12)
    assert json_type == 0x4E4F534A and json_len % 4 == 0
    doc = json.loads(data[20:20 + json_len])
    bin_len, bin_type = struct.unpack_from("<II", data, 20 + json_len)
    assert bin_type == 0x004E4942 and bin_len % 4 == 0
    bin_chunk = data[28 + json_len:28 + json_len + bin_len]
    assert len(data) == 28 + json_len + bin_len

    def view_bytes(index: int) -> bytes:
        bv = doc["bufferViews"][index]
        ext = bv.get("extensions", {}).get("EXT_meshopt_compression")
        if ext is None:
            assert bv["buffer"] == 0
            return bin_chunk[bv.get("byteOffset", 0):bv.get("byteOffset", 0) + bv["byteLength"]]
        import meshoptimizer as mo

        src = bin_chunk[ext.get("byteOffset", 0):ext.get("byteOffset", 0) + ext["byteLength"]]
        if ext["mode"] == "TRIANGLES":
            out = np.asarray(mo.decode_index_buffer(ext["count"], 4, src), np.uint32)
            return out.astype(np.uint16 if ext["byteStride"] == 2 else np.uint32).tobytes()
        return np.asarray(mo.decode_vertex_buffer(ext["count"], ext["byteStride"], src)).view(np.uint8).tobytes()

    dtypes = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
    widths = {"SCALAR": 1, "VEC2": 2, "VEC3": 3}

    def accessor(index: int) -> np.ndarray:
        acc = doc["accessors"][index]
        bv = doc["bufferViews"][acc["bufferView"]]
        dtype = np.dtype(dtypes[acc["componentType"]])
        width = widths[acc["type"]]
        stride = bv.get("byteStride", dtype.itemsize * width)
        raw = np.frombuffer(view_bytes(acc["bufferView"]), np.uint8)
        rows = raw[acc.get("byteOffset", 0):].reshape(-1, stride)[:acc["count"], :dtype.itemsize * width]
        values = np.ascontiguousarray(rows).view(dtype).reshape(acc["count"], width).astype(np.float64)
        if acc.get("normalized"):
            values = np.maximum(values / float(np.iinfo(dtype).max), -1.0)
        return values

    prim = doc["meshes"][0]["primitives"][0]
    node = doc["nodes"][0]
    positions = accessor(prim["attributes"]["POSITION"]) * np.array(node.get("scale", [1, 1, 1])) + np.array(
        node.get("translation", [0, 0, 0]))
    normals = accessor(prim["attributes"]["NORMAL"])
    uvs = accessor(prim["attributes"]["TEXCOORD_0"])
    uvs[:, 1] = 1.0 - uvs[:, 1]
    faces = accessor(prim["indices"]).astype(np.int64).reshape(-1, 3)
    texture = doc["textures"][doc["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"]["index"]]
    image = doc["images"][texture["extensions"]["EXT_texture_webp"]["source"]]
    return {"doc": doc, "positions": positions, "normals": normals / np.linalg.norm(normals, axis=1, keepdims=True),
            "uvs": uvs, "faces": faces, "image": view_bytes(image["bufferView"]), "mime": image["mimeType"]}


def canonical(faces: np.ndarray) -> np.ndarray:
    """Triangles rotated to start at their smallest index and sorted: equal iff same triangles, same winding."""
    start = np.argmin(faces, axis=1)
    rotated = np.take_along_axis(faces, (start[:, None] + np.arange(3)) % 3, axis=1)
    return rotated[np.lexsort(rotated.T[::-1])]


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(255.0**2 / mse)


def check_geometry(baked: BakedTexture, got: dict[str, Any], same_order: bool) -> None:
    """Decoded attributes within the quantization bounds; faces equal (up to corner rotation, and
    up to vertex order unless ``same_order``)."""
    extent = float((baked.vertices.max(0) - baked.vertices.min(0)).max())
    pos_tol = extent / 65535 * 0.5 * (1 + 1e-6) + 1e-12
    uv_tol = 0.5 / 65535 + 1e-9
    in_normals = baked.normals / np.linalg.norm(baked.normals, axis=1, keepdims=True)
    assert len(got["positions"]) == len(baked.vertices)
    if same_order:
        mapping = np.arange(len(baked.vertices))
    else:
        # Match decoded vertices to input ones on (position / extent, uv): unique per seam-split vertex.
        tree = cKDTree(np.hstack([baked.vertices / extent, baked.uvs]))
        dist, mapping = tree.query(np.hstack([got["positions"] / extent, got["uvs"]]))
        assert dist.max() < 1e-3
        assert len(np.unique(mapping)) == len(mapping), "decoded vertices must map one-to-one onto the input"
    assert np.abs(got["positions"] - baked.vertices[mapping]).max() <= pos_tol
    assert np.abs(got["uvs"] - baked.uvs[mapping]).max() <= uv_tol
    # int8 components err by ≤ 0.5/127 each: after renormalising, ≤ ~0.7° (0.012 in length) off.
    assert np.linalg.norm(got["normals"] - in_normals[mapping], axis=1).max() < 0.012
    faces = mapping[got["faces"]]
    np.testing.assert_array_equal(canonical(faces), canonical(baked.faces))


# ---------------------------------------------------------------------------------- round trips


@needs_meshopt
@pytest.mark.parametrize("optimize_order", [True, False])
def test_meshopt_glb_decodes_to_the_input(rng: np.random.Generator, optimize_order: bool) -> None:
    baked = random_baked(rng)
    data, report = encode_web_glb(baked, 50_000_000, compression="meshopt", optimize_order=optimize_order)
    assert report.extensions == (EXT_QUANTIZATION, EXT_MESHOPT, EXT_WEBP)
    got = read_glb(data)
    assert got["doc"]["extensionsRequired"] == list(report.extensions)
    check_geometry(baked, got, same_order=not optimize_order)
    assert report.geometry_bytes < len(baked.vertices) * 16 + baked.faces.size * 2, "meshopt should shrink it"


def test_quantized_glb_decodes_to_the_input_in_order(rng: np.random.Generator) -> None:
    baked = random_baked(rng)
    data, report = encode_web_glb(baked, 50_000_000, compression="none")
    assert report.extensions == (EXT_QUANTIZATION, EXT_WEBP)
    got = read_glb(data)
    check_geometry(baked, got, same_order=True)
    np.testing.assert_array_equal(got["faces"], baked.faces)  # no codec: not even a rotation


def test_webp_texture_decodes_within_psnr_floor(rng: np.random.Generator) -> None:
    baked = random_baked(rng)
    data, report = encode_web_glb(baked, 50_000_000)
    assert (report.texture_size, report.webp_quality, report.attempts) == (len(baked.texture), 90, 1)
    got = read_glb(data)
    assert got["mime"] == "image/webp" and got["image"][:4] == b"RIFF" and got["image"][8:12] == b"WEBP"
    assert report.texture_bytes == len(got["image"])
    image = np.asarray(Image.open(io.BytesIO(got["image"])).convert("RGB"))
    assert image.shape == baked.texture.shape
    # Unflipped: a vertically flipped image would score far below the floor.
    assert psnr(image, baked.texture) >= PSNR_FLOOR_DB


@needs_meshopt
def test_large_mesh_uses_uint32_indices(rng: np.random.Generator) -> None:
    baked = random_baked(rng, texture_size=64, grid=(400, 170))  # > 65535 vertices
    assert len(baked.vertices) > 65535
    data, _ = encode_web_glb(baked, 50_000_000, compression="meshopt", optimize_order=False, min_texture_size=16)
    got = read_glb(data)
    doc = got["doc"]
    assert doc["accessors"][doc["meshes"][0]["primitives"][0]["indices"]]["componentType"] == 5125
    check_geometry(baked, got, same_order=True)


def test_tiling_uvs_fall_back_to_float(rng: np.random.Generator) -> None:
    baked = random_baked(rng, texture_size=64)
    tiled = BakedTexture(**{**baked.__dict__, "uvs": baked.uvs * 3.0 - 1.0})
    got = read_glb(encode_web_glb(tiled, 50_000_000, compression="none")[0])
    assert got["doc"]["accessors"][2]["componentType"] == 5126
    np.testing.assert_allclose(got["uvs"], tiled.uvs, atol=1e-6)


# --------------------------------------------------------------------------------------- budget


def test_budget_met_and_monotone(rng: np.random.Generator, tmp_path: Path) -> None:
    baked = random_baked(rng, texture_size=int(rng.integers(512, 1025)))
    full, full_report = encode_web_glb(baked, 50_000_000)
    # The smallest file the ladder can make: what SizeBudgetError names for a budget just above the geometry.
    with pytest.raises(SizeBudgetError) as geometry_only:
        encode_web_glb(baked, 1)
    with pytest.raises(SizeBudgetError) as ladder:
        encode_web_glb(baked, geometry_only.value.needed_bytes + 1)
    smallest = ladder.value.needed_bytes
    sizes = []
    # From the unconstrained size down to the smallest: every budget met, every smaller budget a file no larger.
    for budget in np.linspace(len(full), smallest, 8).astype(int):
        budget = int(budget)
        path = tmp_path / f"web_{budget}.glb"
        report = write_web_glb(baked, path, budget)
        assert path.stat().st_size == report.total_bytes <= budget
        sizes.append(report.total_bytes)
    assert sizes == sorted(sizes, reverse=True), sizes
    assert sizes[-1] < sizes[0]
    assert full_report.texture_size == len(baked.texture)


def test_budget_too_small_raises_and_writes_nothing(rng: np.random.Generator, tmp_path: Path) -> None:
    baked = random_baked(rng)
    path = tmp_path / "web.glb"
    with pytest.raises(SizeBudgetError, match="geometry alone") as geometry_only:
        write_web_glb(baked, path, 100)
    err = geometry_only.value
    assert err.budget_bytes == 100 and err.needed_bytes > 100 and err.geometry_bytes > 0
    assert str(err.needed_bytes) in str(err) and "100 bytes" in str(err)
    # Room for the geometry but not for even the smallest texture rung.
    budget = err.needed_bytes + 16
    with pytest.raises(SizeBudgetError, match="no rung fits") as ladder:
        write_web_glb(baked, path, budget, min_texture_size=128)
    assert ladder.value.needed_bytes > budget
    assert list(tmp_path.iterdir()) == []  # no file, no temporary left behind
    # The error's figure is achievable: that budget succeeds on the last rung.
    report = write_web_glb(baked, path, ladder.value.needed_bytes, min_texture_size=128)
    assert report.total_bytes == ladder.value.needed_bytes and path.is_file()


# ------------------------------------------------------------------------------------ bad input


def _broken(baked: BakedTexture, **change: Any) -> BakedTexture:
    return BakedTexture(**{**baked.__dict__, **change})


BAD_INPUTS = {
    "nan vertex": lambda b: _broken(b, vertices=np.where(np.arange(len(b.vertices))[:, None] == 3, np.nan,
                                                         b.vertices)),
    "inf uv": lambda b: _broken(b, uvs=np.where(np.arange(len(b.uvs))[:, None] == 0, np.inf, b.uvs)),
    "nan normal": lambda b: _broken(b, normals=np.full_like(b.normals, np.nan)),
    "face index too large": lambda b: _broken(b, faces=np.vstack([b.faces, [[0, 1, len(b.vertices)]]])),
    "negative face index": lambda b: _broken(b, faces=np.vstack([b.faces, [[0, -1, 2]]])),
    "float faces": lambda b: _broken(b, faces=b.faces.astype(np.float64)),
    "no faces": lambda b: _broken(b, faces=np.zeros((0, 3), np.int64)),
    "no vertices": lambda b: _broken(b, vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), np.int64)),
    "uv count": lambda b: _broken(b, uvs=b.uvs[:-1]),
    "texture float": lambda b: _broken(b, texture=b.texture.astype(np.float32)),
    "texture rgba": lambda b: _broken(b, texture=np.dstack([b.texture, b.texture[..., :1]])),
    "texture not square": lambda b: _broken(b, texture=b.texture[:-1]),
    "texture grey": lambda b: _broken(b, texture=b.texture[..., 0]),
}


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_bad_input_is_rejected_before_writing(rng: np.random.Generator, tmp_path: Path, case: str) -> None:
    baked = BAD_INPUTS[case](random_baked(rng, texture_size=64))
    path = tmp_path / "web.glb"
    with pytest.raises(ValueError) as err:
        write_web_glb(baked, path, 50_000_000)
    assert not isinstance(err.value, SizeBudgetError)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("budget", [0, -5, 1.5e6, True])
def test_bad_budget_is_rejected(rng: np.random.Generator, budget: Any) -> None:
    with pytest.raises(ValueError, match="budget_bytes"):
        encode_web_glb(random_baked(rng, texture_size=64), budget)


# ----------------------------------------------------------------------- the loaders' decoders

_JS_DECODE = """
const [decoderUrl, glbPath] = process.argv.slice(-2);
const { MeshoptDecoder } = await import(decoderUrl);
const { readFileSync } = await import('node:fs');
const glb = readFileSync(glbPath);
const jsonLength = glb.readUInt32LE(12);
const doc = JSON.parse(glb.subarray(20, 20 + jsonLength).toString());
const bin = glb.subarray(28 + jsonLength);
await MeshoptDecoder.ready;
const out = {};
doc.bufferViews.forEach((view, i) => {
  const ext = (view.extensions || {}).EXT_meshopt_compression;
  if (!ext) return;
  const source = bin.subarray(ext.byteOffset || 0, (ext.byteOffset || 0) + ext.byteLength);
  const target = new Uint8Array(ext.count * ext.byteStride);
  MeshoptDecoder.decodeGltfBuffer(target, ext.count, ext.byteStride, source, ext.mode, ext.filter || 'NONE');
  out[i] = Buffer.from(target).toString('base64');
});
process.stdout.write(JSON.stringify(out));
"""


@needs_meshopt
def test_meshopt_js_decoder_agrees(rng: np.random.Generator, tmp_path: Path) -> None:
    """three.js and model-viewer decode with meshoptimizer's JS decoder, not with the Python binding."""
    if NODE is None or not MESHOPT_JS.is_file():
        pytest.skip(f"needs node and {MESHOPT_JS} (`npm ci --prefix tools/web`)")
    import base64

    baked = random_baked(rng)
    data, _ = encode_web_glb(baked, 50_000_000, compression="meshopt")
    path = tmp_path / "web.glb"
    path.write_bytes(data)
    proc = subprocess.run([NODE, "--input-type=module", "-e", _JS_DECODE, "--", MESHOPT_JS.as_uri(), str(path)],
                          capture_output=True, text=True, timeout=60, check=True)
    decoded = {int(k): base64.b64decode(v) for k, v in json.loads(proc.stdout).items()}
    got = read_glb(data)
    doc = got["doc"]
    assert sorted(decoded) == [i for i, bv in enumerate(doc["bufferViews"]) if "extensions" in bv]
    faces = np.frombuffer(decoded[doc["accessors"][3]["bufferView"]],
                          np.uint16 if doc["accessors"][3]["componentType"] == 5123 else np.uint32)
    np.testing.assert_array_equal(faces.reshape(-1, 3), got["faces"])
    pos_view = decoded[doc["accessors"][0]["bufferView"]]
    q = np.frombuffer(pos_view, np.uint16).reshape(-1, 4)[:, :3].astype(np.float64) / 65535
    node = doc["nodes"][0]
    np.testing.assert_allclose(q * node["scale"] + node["translation"], got["positions"], rtol=0, atol=1e-12)
