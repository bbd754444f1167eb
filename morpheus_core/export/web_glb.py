"""A web-sized GLB of a baked asset: quantized (and meshopt-compressed) geometry, a WebP texture, a byte budget.

The GLB of ``morpheus_core.export.gltf`` (float attributes, PNG texture) stays the copy for editing
and archiving; this module writes a second, *web* copy for product pages, where download size is
what matters and the loader is three.js / model-viewer. It writes the glTF 2.0 binary itself (JSON
and BIN chunks, 4-byte aligned) rather than through trimesh, because trimesh can write neither
quantized attributes nor compressed buffer views nor WebP images.

What the web copy contains, and why:

* ``KHR_mesh_quantization``: positions as uint16 (normalized) dequantized by the mesh node's
  translation and *uniform* scale (a non-uniform node scale would also skew the normals, which
  renderers transform by the inverse transpose), normals as int8 normalized, texture coordinates
  as uint16 normalized (v flipped to glTF's top-left origin, v_gltf = 1 − v; float32 if a
  coordinate lies outside [0, 1], which uint16 normalized cannot hold). Error bounds: half a step,
  i.e. extent / 131070 per position axis, 1/254 per normal component (before renormalisation),
  1/131070 per UV coordinate.
* ``EXT_meshopt_compression`` on top (mode ATTRIBUTES per vertex stream, TRIANGLES for indices,
  codec versions 0 and 1 as that extension requires), when the PyPI ``meshoptimizer`` binding is
  importable (``compression="auto"``), after meshoptimizer's vertex-cache / vertex-fetch reordering
  (``optimize_order``: both codecs predict from stream neighbours; on a 50k-face xatlas mesh this
  takes the compressed geometry from 399 to 313 kB). So the web copy holds the input's vertices
  and triangles in another order, and the index codec may rotate a triangle's corners
  (a, b, c → b, c, a: same winding). Chosen over Draco (``KHR_draco_mesh_compression``) because
  it keeps the quantized GPU layout (the decoder restores the buffer views as they were), decodes
  much faster, and model-viewer already bundles its decoder (see below). The binding is an alpha
  release (0.2.30a0, built from source: it needs a C++ compiler), so every compressed stream is
  decoded again here and compared with its source (vertex bytes exactly, triangles up to that
  rotation) before it is used; if the check fails, ``auto`` falls back to plain quantization with
  a warning. The compressed data lives in the GLB chunk (buffer 0); buffer 1 is the extension's
  uri-less *fallback* buffer (``"fallback": true``), which only sizes the decoded views, so the
  extension is listed as required. The Khronos validator (2.0.0-dev.3.10) does not know this
  extension: it reports one info (UNSUPPORTED_EXTENSION) and cannot check the compressed views'
  data; ``compression="none"`` writes the same file uncompressed, which it checks fully.
* ``EXT_texture_webp`` as a **required** extension with **no** PNG/JPEG fallback image: a fallback
  would cost bytes under the same budget, and it could never be used — any loader that does not
  know EXT_texture_webp does not know EXT_meshopt_compression either (three.js, Babylon.js and
  model-viewer know both; every current browser decodes WebP). Without meshopt the file is still
  unreadable to such a loader, because KHR_mesh_quantization is required too.

Budget: the geometry is encoded once; the texture then walks a fixed ladder — every WebP quality of
``qualities`` (highest first) at full size, then the same at half size, and so on down to
``min_texture_size`` — and the first rung whose whole GLB fits ``budget_bytes`` wins. Since the
ladder is fixed, a smaller budget never gives a larger file. When even the last rung does not fit
(or the geometry alone does not), ``SizeBudgetError`` says how many bytes were needed.

Viewing it in model-viewer: model-viewer 4.4 bundles the meshopt decoder but only enables it once
``self.ModelViewerElement = {meshoptDecoderLocation: URL}`` is set before the element is created,
and URL loads as a classic script: vendor ``tools/web/node_modules/meshoptimizer/meshopt_decoder.cjs``
(UMD; serve it as ``meshopt_decoder.js`` with a JavaScript MIME type). three.js alone:
``GLTFLoader.setMeshoptDecoder`` with the same decoder.
"""

from __future__ import annotations

import io
import json
import math
import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, features

from morpheus_core.export.glb_geometry import (
    EXT_MESHOPT,
    Compression,
    Geometry,
    encode_geometry,
    pad4,
)
from morpheus_core.geometry.textured_mesh import BakedTexture
from morpheus_core.runtime.atomic_io import atomic_write_bytes

WEBP_QUALITIES: tuple[int, ...] = (90, 80, 70, 60, 50)
"""WebP qualities tried at each texture size, best first. The ladder halves the texture rather than going
below 50, where WebP's block artefacts start to show on smooth albedo (a judgement, not a measurement)."""

MIN_TEXTURE_SIZE = 128
"""The texture is never halved below this side (texels): smaller is too blurry for a product page."""

EXT_WEBP = "EXT_texture_webp"

# glTF enums.
_LINEAR, _LINEAR_MIPMAP_LINEAR, _CLAMP_TO_EDGE = 9729, 9987, 33071

_GLB_MAGIC, _GLB_VERSION = b"glTF", 2
_CHUNK_JSON, _CHUNK_BIN = 0x4E4F534A, 0x004E4942
_WEBP_MAX_SIDE = 16383  # libwebp's limit per side



class SizeBudgetError(ValueError):
    """The web GLB cannot be made to fit the byte budget (even at the smallest texture rung)."""

    def __init__(self, needed_bytes: int, budget_bytes: int, geometry_bytes: int, detail: str) -> None:
        self.needed_bytes = needed_bytes
        self.budget_bytes = budget_bytes
        self.geometry_bytes = geometry_bytes
        super().__init__(f"web GLB needs at least {needed_bytes} bytes but the budget is {budget_bytes} bytes "
                         f"(geometry {geometry_bytes} bytes): {detail}")


@dataclass(frozen=True)
class WebGlbReport:
    """What ``encode_web_glb`` wrote and at which rung of the texture ladder it stopped."""

    total_bytes: int
    """Size of the GLB (≤ the budget)."""
    texture_size: int
    """Side of the (square) WebP texture in texels."""
    webp_quality: int
    """WebP quality (0–100) of the texture."""
    extensions: tuple[str, ...]
    """glTF extensions used (all of them are also required)."""
    geometry_bytes: int
    """Bytes of vertex and index data in the BIN chunk (compressed if meshopt is used)."""
    texture_bytes: int
    """Bytes of the WebP image."""
    budget_bytes: int
    """The budget it was made for."""
    attempts: int
    """Texture encodings tried before one fitted (1 = the first rung)."""


# ---------------------------------------------------------------------------------------------- input


def _check_input(baked: BakedTexture) -> None:
    """Reject malformed assets before any encoding: a bad web copy would fail only in a browser."""
    v, f, uv, nrm, tex = baked.vertices, baked.faces, baked.uvs, baked.normals, baked.texture
    arrays = {"vertices": v, "faces": f, "uvs": uv, "normals": nrm, "texture": tex}
    for name, arr in arrays.items():
        if not isinstance(arr, np.ndarray):
            raise ValueError(f"{name} must be a numpy array, got {type(arr).__name__}")
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise ValueError(f"vertices must be (N, 3) with N ≥ 1, got shape {v.shape}")
    n = len(v)
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ValueError(f"faces must be (F, 3) with F ≥ 1, got shape {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"faces must have an integer dtype, got {f.dtype}")
    if f.min() < 0 or f.max() >= n:
        raise ValueError(f"faces index vertices out of range [0, {n}): min {f.min()}, max {f.max()}")
    if n > 2**32 - 1:
        raise ValueError(f"{n} vertices exceed glTF's uint32 indices")
    for name, arr, cols in (("uvs", uv, 2), ("normals", nrm, 3)):
        if arr.shape != (n, cols):
            raise ValueError(f"{name} must be ({n}, {cols}) (one per vertex), got shape {arr.shape}")
    for name, arr in (("vertices", v), ("uvs", uv), ("normals", nrm)):
        if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
            raise ValueError(f"{name} must be real numbers, got dtype {arr.dtype}")
        if not np.isfinite(arr).all():
            raise ValueError(f"{name} contain NaN or Inf")
    if tex.dtype != np.uint8:
        raise ValueError(f"texture must be uint8, got {tex.dtype}")
    if tex.ndim != 3 or tex.shape[2] != 3 or tex.shape[0] != tex.shape[1] or tex.shape[0] < 1:
        raise ValueError(f"texture must be (S, S, 3), got shape {tex.shape}")
    if tex.shape[0] > _WEBP_MAX_SIDE:
        raise ValueError(f"texture side {tex.shape[0]} exceeds WebP's limit of {_WEBP_MAX_SIDE}")


# ---------------------------------------------------------------------------------------------- GLB


def _assemble(geometry: Geometry, webp: bytes | None) -> bytes:
    """The GLB: JSON chunk + BIN chunk (geometry streams, then the WebP image), everything 4-byte aligned.

    ``webp=None`` leaves the image out (used to size the geometry alone against the budget)."""
    bin_parts: list[bytes] = []
    offset = 0

    def put(data: bytes) -> int:
        nonlocal offset
        start = offset
        bin_parts.append(data + b"\0" * (pad4(len(data)) - len(data)))
        offset += pad4(len(data))
        return start

    buffer_views: list[dict[str, Any]] = []
    fallback_offset = 0
    for view in geometry.views:
        bv: dict[str, Any] = {"target": view.target}
        if view.stride:
            bv["byteStride"] = view.stride
        if geometry.meshopt and view.compressed is not None:
            # The decoded view lives in the data-less fallback buffer 1; its bytes come from buffer 0.
            ext: dict[str, Any] = {"buffer": 0, "byteOffset": put(view.compressed), "byteLength": len(view.compressed),
                                   "byteStride": view.stride or view.index_size, "count": view.count,
                                   "mode": view.mode}
            bv.update(buffer=1, byteOffset=fallback_offset, byteLength=len(view.raw),
                      extensions={EXT_MESHOPT: ext})
            fallback_offset += pad4(len(view.raw))
        else:
            bv.update(buffer=0, byteOffset=put(view.raw), byteLength=len(view.raw))
        buffer_views.append(bv)

    accessors = [dict(acc, bufferView=i) for i, acc in enumerate(geometry.accessors)]
    primitive: dict[str, Any] = {"attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2}, "indices": 3,
                                 "mode": 4}
    # glTF's default metallic factor is 1 (a black mirror): say "dielectric, matte" like the editing GLB.
    pbr: dict[str, Any] = {"metallicFactor": 0.0, "roughnessFactor": 1.0}
    extensions = list(geometry.extensions)
    doc: dict[str, Any] = {
        "asset": {"version": "2.0", "generator": "morpheus3d web_glb"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "translation": list(geometry.translation), "scale": [geometry.scale] * 3}],
        "meshes": [{"primitives": [primitive]}],
        "accessors": accessors,
        "bufferViews": buffer_views,
    }
    if webp is not None:
        image_view = len(buffer_views)
        buffer_views.append({"buffer": 0, "byteOffset": put(webp), "byteLength": len(webp)})
        doc["images"] = [{"bufferView": image_view, "mimeType": "image/webp"}]
        doc["samplers"] = [{"magFilter": _LINEAR, "minFilter": _LINEAR_MIPMAP_LINEAR,
                            # An atlas has no tiling: clamping keeps border texels from bleeding across.
                            "wrapS": _CLAMP_TO_EDGE, "wrapT": _CLAMP_TO_EDGE}]
        # No core `source`: the WebP image is the only one (see the module docstring).
        doc["textures"] = [{"sampler": 0, "extensions": {EXT_WEBP: {"source": 0}}}]
        pbr["baseColorTexture"] = {"index": 0}
        extensions.append(EXT_WEBP)
    primitive["material"] = 0
    doc["materials"] = [{"pbrMetallicRoughness": pbr}]
    buffers: list[dict[str, Any]] = [{"byteLength": offset}]
    if geometry.meshopt:
        buffers.append({"byteLength": fallback_offset, "extensions": {EXT_MESHOPT: {"fallback": True}}})
    doc["buffers"] = buffers
    doc["extensionsUsed"] = extensions
    doc["extensionsRequired"] = extensions

    json_bytes = json.dumps(doc, separators=(",", ":")).encode()
    json_bytes += b" " * (pad4(len(json_bytes)) - len(json_bytes))  # the spec pads JSON with spaces
    bin_bytes = b"".join(bin_parts)
    total = 12 + 8 + len(json_bytes) + 8 + len(bin_bytes)
    return b"".join([
        struct.pack("<4sII", _GLB_MAGIC, _GLB_VERSION, total),
        struct.pack("<II", len(json_bytes), _CHUNK_JSON), json_bytes,
        struct.pack("<II", len(bin_bytes), _CHUNK_BIN), bin_bytes,
    ])


# -------------------------------------------------------------------------------------------- texture


def _webp(image: Image.Image, quality: int, method: int) -> bytes:
    out = io.BytesIO()
    image.save(out, format="WEBP", quality=quality, method=method)
    return out.getvalue()


def _texture_ladder(texture: np.ndarray, qualities: Sequence[int], min_size: int,
                    ) -> Iterator[tuple[Image.Image, int]]:
    """(image, quality) rungs in budget order: all qualities at a size, then half that size, and so on.

    Halving is a 2×2 box filter (``Image.reduce``): exact averaging, no ringing at the sharp seams."""
    image = Image.fromarray(np.ascontiguousarray(texture))  # (S, S, 3) uint8: RGB
    while True:
        for q in qualities:
            yield image, q
        if image.width // 2 < min_size:
            return
        image = image.reduce(2)


# -------------------------------------------------------------------------------------------- public


def encode_web_glb(baked: BakedTexture, budget_bytes: int, *, qualities: Sequence[int] = WEBP_QUALITIES,
                   min_texture_size: int = MIN_TEXTURE_SIZE, compression: Compression = "auto",
                   optimize_order: bool = True, webp_method: int = 6) -> tuple[bytes, WebGlbReport]:
    """The web copy of ``baked`` as GLB bytes of at most ``budget_bytes``, and what went into it.

    ``qualities``: WebP qualities tried at each texture size, in order; ``min_texture_size``: the
    smallest side the texture is halved down to (the input's size if that is smaller);
    ``compression``: ``"auto"`` (meshopt when its binding is usable, else quantization only, with a
    warning), ``"meshopt"`` (RuntimeError when unusable) or ``"none"`` (quantization only);
    ``optimize_order``: reorder triangles and vertices for the GPU caches and meshopt's codecs
    (only with meshopt; the input order is kept otherwise, up to meshopt's triangle rotation);
    ``webp_method``: libwebp's effort 0–6 (6: ~1–2 % smaller files than 4 for ~1.5× its time).

    Raises ValueError for malformed input (before any work) and ``SizeBudgetError`` when nothing on
    the ladder fits. The editing GLB (``morpheus_core.export.gltf``) is not replaced by this copy."""
    _check_input(baked)
    if isinstance(budget_bytes, bool) or not isinstance(budget_bytes, int | np.integer) or budget_bytes <= 0:
        raise ValueError(f"budget_bytes must be a positive integer, got {budget_bytes!r}")
    if not qualities or any(not 0 <= int(q) <= 100 for q in qualities):
        raise ValueError(f"qualities must be a non-empty sequence of 0–100, got {qualities!r}")
    if min_texture_size < 1:
        raise ValueError(f"min_texture_size must be ≥ 1, got {min_texture_size}")
    if compression not in ("auto", "meshopt", "none"):
        raise ValueError(f"compression must be 'auto', 'meshopt' or 'none', got {compression!r}")
    if not features.check("webp"):
        raise RuntimeError("this Pillow build cannot encode WebP (PIL.features.check('webp') is False)")

    geometry = encode_geometry(baked, compression, optimize_order)
    bare = len(_assemble(geometry, None))
    if bare > budget_bytes:
        raise SizeBudgetError(bare, int(budget_bytes), geometry.stored_bytes,
                              "the geometry alone is over budget (decimate the mesh or raise the budget)")
    smallest = math.inf
    attempts = 0
    for image, quality in _texture_ladder(baked.texture, [int(q) for q in qualities], min_texture_size):
        attempts += 1
        webp = _webp(image, quality, webp_method)
        glb = _assemble(geometry, webp)
        if len(glb) <= budget_bytes:
            report = WebGlbReport(total_bytes=len(glb), texture_size=image.width, webp_quality=quality,
                                  extensions=(*geometry.extensions, EXT_WEBP), geometry_bytes=geometry.stored_bytes,
                                  texture_bytes=len(webp), budget_bytes=int(budget_bytes), attempts=attempts)
            return glb, report
        smallest = min(smallest, len(glb))
    raise SizeBudgetError(int(smallest), int(budget_bytes), geometry.stored_bytes,
                          f"no rung fits, down to a {image.width} px texture at WebP quality {quality}")


def write_web_glb(baked: BakedTexture, path: Path | str, budget_bytes: int, **options: Any) -> WebGlbReport:
    """Encode (``encode_web_glb``, same ``options``) and write ``path`` atomically; nothing is written
    when encoding fails (bad input, budget not met)."""
    data, report = encode_web_glb(baked, budget_bytes, **options)
    atomic_write_bytes(Path(path), data)
    return report
