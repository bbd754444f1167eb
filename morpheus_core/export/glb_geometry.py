"""The web GLB's geometry streams: ``KHR_mesh_quantization`` attributes and, where the PyPI ``meshoptimizer``
binding works, ``EXT_meshopt_compression`` on top (``morpheus_core.export.web_glb`` assembles the file and says
why each choice was made). Every compressed stream is decoded again and compared before it is used.
"""

from __future__ import annotations

import threading
import warnings
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from morpheus_core.geometry.textured_mesh import BakedTexture

Compression = Literal["auto", "meshopt", "none"]

EXT_QUANTIZATION = "KHR_mesh_quantization"
EXT_MESHOPT = "EXT_meshopt_compression"

# glTF enums.
BYTE, UNSIGNED_SHORT, UNSIGNED_INT, FLOAT = 5120, 5123, 5125, 5126
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963

_UV_EPS = 1e-6  # float noise around [0, 1] that is still clipped into uint16 range

# meshoptimizer's encoder versions are process-global settings: set and use them under one lock.
_MESHOPT_LOCK = threading.Lock()


@dataclass(frozen=True)
class Stream:
    """One geometry stream: raw (quantized) bytes plus, with meshopt, its compressed form."""

    raw: bytes
    stride: int  # 0 for indices (no byteStride on index views)
    count: int  # elements (vertices or indices)
    target: int
    compressed: bytes | None = None
    mode: str = "ATTRIBUTES"
    index_size: int = 0  # 2 or 4 for index streams


@dataclass(frozen=True)
class Geometry:
    """The encoded geometry: its streams, accessors (minus bufferView indices) and node transform."""

    views: tuple[Stream, ...]  # POSITION, NORMAL, TEXCOORD_0, indices — in that order
    accessors: tuple[dict[str, Any], ...]
    translation: tuple[float, float, float]
    scale: float
    extensions: tuple[str, ...]

    @property
    def meshopt(self) -> bool:
        return EXT_MESHOPT in self.extensions

    @property
    def stored_bytes(self) -> int:
        """Bytes of geometry in the GLB's BIN chunk, with 4-byte alignment."""
        return sum(pad4(len(v.compressed if self.meshopt and v.compressed is not None else v.raw)) for v in self.views)


def pad4(n: int) -> int:
    return (n + 3) & ~3


# ------------------------------------------------------------------------------------------- geometry


@dataclass(frozen=True)
class _Mesh:
    """The arrays that go into the GLB (float64 attributes, int64 faces), in their final order."""

    vertices: np.ndarray
    normals: np.ndarray
    uvs: np.ndarray
    faces: np.ndarray


def _quantize(mesh: _Mesh) -> tuple[list[Stream], list[dict[str, Any]], tuple[float, float, float], float]:
    """KHR_mesh_quantization streams (one buffer view per attribute: each compresses better alone)."""
    pos = mesh.vertices
    n = len(pos)
    lo, hi = pos.min(0), pos.max(0)
    extent = float((hi - lo).max())
    if extent <= 0.0:  # all vertices at one point: any scale dequantizes them exactly
        extent = 1.0
    q_pos = np.rint((pos - lo) / extent * 65535.0).clip(0, 65535).astype(np.uint16)
    # Attribute elements must start on 4-byte boundaries: pad xyz (6 bytes) to a stride of 8.
    pos_block = np.zeros((n, 4), np.uint16)
    pos_block[:, :3] = q_pos

    length = np.linalg.norm(mesh.normals, axis=1, keepdims=True)
    # A zero normal has no direction to keep; +Z is as good as any and keeps the accessor unit-length.
    nrm = np.where(length > 1e-12, mesh.normals / np.maximum(length, 1e-12), [0.0, 0.0, 1.0])
    nrm_block = np.zeros((n, 4), np.int8)
    nrm_block[:, :3] = np.rint(nrm * 127.0).clip(-127, 127).astype(np.int8)

    uv = mesh.uvs.copy()
    uv[:, 1] = 1.0 - uv[:, 1]  # glTF's UV origin is the image's top-left corner
    if uv.min() >= -_UV_EPS and uv.max() <= 1.0 + _UV_EPS:
        uv_block = np.rint(uv.clip(0.0, 1.0) * 65535.0).astype(np.uint16)
        uv_type, uv_norm = UNSIGNED_SHORT, True
    else:  # tiling coordinates: uint16 normalized cannot hold them
        uv_block = uv.astype(np.float32)
        uv_type, uv_norm = FLOAT, False

    # uint16 only while the largest index stays below 65535 (that value is primitive restart).
    index_size = 2 if n <= 65535 else 4
    indices = mesh.faces.reshape(-1).astype(np.uint16 if index_size == 2 else np.uint32)

    views = [
        Stream(pos_block.tobytes(), 8, n, ARRAY_BUFFER),
        Stream(nrm_block.tobytes(), 4, n, ARRAY_BUFFER),
        Stream(uv_block.tobytes(), uv_block.itemsize * 2, n, ARRAY_BUFFER),
        Stream(indices.tobytes(), 0, len(indices), ELEMENT_ARRAY_BUFFER, mode="TRIANGLES", index_size=index_size),
    ]
    accessors: list[dict[str, Any]] = [
        # min/max hold stored (integer) values, normalized or not: the validator checks them that way.
        {"componentType": UNSIGNED_SHORT, "normalized": True, "count": n, "type": "VEC3",
         "min": q_pos.min(0).tolist(), "max": q_pos.max(0).tolist()},
        {"componentType": BYTE, "normalized": True, "count": n, "type": "VEC3"},
        {"componentType": uv_type, "count": n, "type": "VEC2", **({"normalized": True} if uv_norm else {})},
        {"componentType": UNSIGNED_SHORT if index_size == 2 else UNSIGNED_INT, "count": len(indices),
         "type": "SCALAR"},
    ]
    translation = (float(lo[0]), float(lo[1]), float(lo[2]))
    return views, accessors, translation, extent


def meshopt_available() -> str | None:
    """None when the ``meshoptimizer`` binding can be used, else why not (and the fix)."""
    try:
        import meshoptimizer  # noqa: F401
    except Exception as exc:  # the binding raises ImportError, a broken build OSError
        return (f"the meshoptimizer Python binding is not usable ({exc}); install it with "
                "`make install` (meshoptimizer==0.2.30a0 is a dependency, an sdist: needs a C++ compiler, g++)")
    return None


def _canonical_triangles(faces: np.ndarray) -> np.ndarray:
    """Triangles as sorted rows, each rotated to start at its smallest index (rotation keeps the winding)."""
    faces = faces.reshape(-1, 3)
    start = np.argmin(faces, axis=1)
    rotated = np.take_along_axis(faces, (start[:, None] + np.arange(3)[None, :]) % 3, axis=1)
    return rotated[np.lexsort(rotated.T[::-1])]


def _same_triangles(a: np.ndarray, b: np.ndarray) -> bool:
    return a.size == b.size and np.array_equal(_canonical_triangles(a), _canonical_triangles(b))


def _optimize_order(mesh: _Mesh) -> _Mesh:
    """Triangles in vertex-cache order, vertices in first-use order (meshoptimizer's optimizers).

    Both codecs predict from neighbours in the stream, so this ordering is what makes them work:
    on a 50k-face xatlas mesh it takes the compressed geometry from 399 to 313 kB (the index
    stream alone halves). Unreferenced vertices are kept, at the end."""
    import meshoptimizer as mo

    n = len(mesh.vertices)
    flat = mesh.faces.reshape(-1).astype(np.uint32)
    cached = np.zeros_like(flat)
    mo.optimize_vertex_cache(cached, flat, len(flat), n)
    remap = np.zeros(n, np.uint32)
    used = int(mo.optimize_vertex_fetch_remap(remap, cached, len(cached), n))
    unused = remap == np.uint32(0xFFFFFFFF)
    remap = remap.astype(np.int64)
    remap[unused] = used + np.arange(int(unused.sum()))
    # The binding is an alpha: use its answer only if it is a triangle permutation and a vertex bijection.
    if not _same_triangles(cached, flat) or not np.array_equal(np.sort(remap), np.arange(n)):
        raise RuntimeError("meshoptimizer's reordering returned an inconsistent mesh")
    order = np.empty(n, np.int64)
    order[remap] = np.arange(n)  # new vertex i is old vertex order[i]
    return _Mesh(mesh.vertices[order], mesh.normals[order], mesh.uvs[order],
                 remap[cached.astype(np.int64)].reshape(-1, 3))


def _meshopt_compress(views: list[Stream]) -> list[Stream]:
    """Each stream meshopt-encoded (vertex codec v0, index codec v1: what EXT_meshopt_compression allows)
    and decoded again; raises RuntimeError when a round trip differs.

    The index codec may rotate a triangle's corners (a, b, c → b, c, a: same triangle, same winding);
    the decoded order is what a loader gets, so it replaces the raw stream."""
    import meshoptimizer as mo

    out = []
    with _MESHOPT_LOCK:
        mo.encode_vertex_version(0)
        mo.encode_index_version(1)
        for view in views:
            raw = view.raw
            if view.mode == "TRIANGLES":
                dtype = np.uint16 if view.index_size == 2 else np.uint32
                flat = np.frombuffer(raw, dtype).astype(np.uint32)
                data = mo.encode_index_buffer(flat, len(flat), int(flat.max()) + 1)
                back = np.asarray(mo.decode_index_buffer(len(flat), 4, data), dtype=np.uint32)
                ok = _same_triangles(back, flat)
                raw = back.astype(dtype).tobytes()
            else:
                block = np.frombuffer(raw, np.uint8).reshape(view.count, view.stride)
                data = mo.encode_vertex_buffer(block, view.count, view.stride)
                back = np.asarray(mo.decode_vertex_buffer(view.count, view.stride, data)).view(np.uint8)
                ok = back.tobytes() == raw
            if not ok:
                raise RuntimeError(f"meshopt round trip changed a {view.mode} stream: the binding is broken")
            out.append(Stream(raw, view.stride, view.count, view.target, bytes(data), view.mode, view.index_size))
    return out


def encode_geometry(baked: BakedTexture, compression: Compression, optimize_order: bool) -> Geometry:
    mesh = _Mesh(np.asarray(baked.vertices, np.float64), np.asarray(baked.normals, np.float64),
                 np.asarray(baked.uvs, np.float64), np.asarray(baked.faces, np.int64))
    why = meshopt_available() if compression != "none" else None
    if why is not None:
        if compression == "meshopt":
            raise RuntimeError(why)
        warnings.warn(f"{why}; writing quantized geometry without compression", stacklevel=3)
    if compression != "none" and why is None:
        try:
            packed = _optimize_order(mesh) if optimize_order else mesh
            views, accessors, translation, scale = _quantize(packed)
            views = _meshopt_compress(views)
            return Geometry(tuple(views), tuple(accessors), translation, scale, (EXT_QUANTIZATION, EXT_MESHOPT))
        except (RuntimeError, ValueError, OSError) as exc:  # what the binding raises when it misbehaves
            if compression == "meshopt":
                raise RuntimeError(f"meshopt compression failed: {exc}") from exc
            warnings.warn(f"meshopt compression failed ({exc}); writing quantized geometry without it",
                          stacklevel=3)
    views, accessors, translation, scale = _quantize(mesh)
    return Geometry(tuple(views), tuple(accessors), translation, scale, (EXT_QUANTIZATION,))
