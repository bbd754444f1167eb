"""Export of a baked asset (``geometry.textured_mesh.BakedTexture``) as GLB or OBJ + MTL + PNG.

``encode_glb`` / ``encode_obj`` return bytes (for callers that write through the asset store; ``decode_glb``
reads the GLB back);
``export_glb`` / ``export_obj`` write files atomically (``morpheus_core.runtime.atomic_io``). The texture
(row 0 at v = 1) is handed to trimesh unflipped; trimesh writes glTF's top-left UV origin itself.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image

from morpheus_core.geometry.textured_mesh import BakedTexture
from morpheus_core.runtime.atomic_io import atomic_write_bytes


def _trimesh(baked: BakedTexture) -> trimesh.Trimesh:
    # glTF's default metallic factor is 1 (a black mirror in most viewers): say "dielectric, matte".
    material = trimesh.visual.material.PBRMaterial(
        baseColorTexture=Image.fromarray(baked.texture), metallicFactor=0.0, roughnessFactor=1.0)
    return trimesh.Trimesh(vertices=baked.vertices, faces=baked.faces, vertex_normals=baked.normals,
                           visual=trimesh.visual.TextureVisuals(uv=baked.uvs, material=material), process=False)


def encode_glb(baked: BakedTexture) -> bytes:
    """The asset as GLB bytes (PBR base-colour texture, smooth normals)."""
    return trimesh.exchange.gltf.export_glb(_trimesh(baked), include_normals=True)


def decode_glb(data: bytes) -> BakedTexture:
    """The asset back from ``encode_glb``'s bytes: vertices, faces, UVs (v up), the written normals (read from
    the file, not recomputed) and the base-colour texture; ``coverage`` is not in a GLB (NaN)."""
    loaded = trimesh.exchange.gltf.load_glb(io.BytesIO(data))
    geometries = list(loaded["geometry"].values())
    if len(geometries) != 1:
        raise ValueError(f"expected one mesh in the GLB, found {len(geometries)}")
    g = geometries[0]
    visual = g["visual"]
    texture = np.asarray(visual.material.baseColorTexture.convert("RGB"))
    faces = np.asarray(g["faces"], dtype=np.int64)
    return BakedTexture(np.asarray(g["vertices"], np.float32), faces, np.asarray(visual.uv, np.float32),
                        np.asarray(g["vertex_normals"], np.float32), texture, float("nan"), int(faces.shape[0]))


def encode_obj(baked: BakedTexture, stem: str) -> dict[str, bytes]:
    """``{stem}.obj``, ``{stem}.mtl`` and ``{stem}.png`` as bytes. Written here rather than through
    trimesh so the MTL says Kd 1 (map_Kd is multiplied by Kd; trimesh's PBR conversion writes 0.4)."""
    out = io.StringIO()
    out.write(f"mtllib {stem}.mtl\nusemtl {stem}\n")
    np.savetxt(out, baked.vertices, fmt="v %.7g %.7g %.7g")
    np.savetxt(out, baked.uvs, fmt="vt %.7g %.7g")
    np.savetxt(out, baked.normals, fmt="vn %.6g %.6g %.6g")
    idx = np.repeat(baked.faces + 1, 3, axis=1)  # v/vt/vn share one index: vertices are split at seams
    np.savetxt(out, idx, fmt="f %d/%d/%d %d/%d/%d %d/%d/%d")
    mtl = f"newmtl {stem}\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nd 1\nillum 1\nmap_Kd {stem}.png\n"
    png = io.BytesIO()
    Image.fromarray(baked.texture).save(png, format="PNG")
    return {f"{stem}.obj": out.getvalue().encode(), f"{stem}.mtl": mtl.encode(), f"{stem}.png": png.getvalue()}


def export_glb(baked: BakedTexture, path: Path | str) -> Path:
    """Write the asset to ``path`` as GLB, atomically."""
    return atomic_write_bytes(Path(path), encode_glb(baked))


def export_obj(baked: BakedTexture, path: Path | str) -> Path:
    """Write ``path`` (.obj) with its .mtl and .png beside it, each atomically; the .obj, which
    references the others, is written last, so a present .obj always has its material and texture."""
    path = Path(path)
    files = encode_obj(baked, path.stem)
    obj_name = f"{path.stem}.obj"
    for name, data in files.items():
        if name != obj_name:
            atomic_write_bytes(path.with_name(name), data)
    return atomic_write_bytes(path, files[obj_name])
