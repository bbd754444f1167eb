"""UV-textured meshes: load a GLB / OBJ asset, sample its texture, render it, sample its surface.

The counterpart of ``morpheus_core.export``'s bake and export: what we write (or any single-texture
asset) can be read back and rendered with the same rasteriser, so exported assets are evaluated with
the same cameras, conventions and losses as the optimised mesh and colour field.

* Texture orientation: ``uvs`` have v up and the image has **row 0 at v = 1** — the OBJ / trimesh
  convention of ``bake_uv``. trimesh flips glTF's top-left-origin v (v ↦ 1 − v) on import as it does
  on export, so GLB and OBJ assets both arrive in this convention and the image is used unflipped
  (``tests/test_textured.py`` checks it by rendering both files against the analytic colour field).
* ``sample_texture``: bilinear with texel centres at ((j + ½)/W, 1 − (i + ½)/H) and clamp-to-edge,
  through ``grid_sample`` so gradients reach the texture and the UVs.
* ``render_textured``: ``render_mesh``'s pipeline (``render_shaded``) with the colour of a covered
  pixel taken from the texture at the perspective-correct interpolated UV. It rasterises the geometry
  with the UV-seam copies of each vertex merged (``TexturedMesh.welded``), so opacity, depth and
  normals equal ``render_mesh``'s for the unsplit mesh (seam edges would otherwise pass for open
  boundaries in the silhouette search and blur pixels next to the true silhouette).
* Only the base-colour image is read: colour factors (glTF ``baseColorFactor``, OBJ ``Kd``), alpha
  and other PBR maps are ignored.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
import trimesh
from PIL import Image
from torch import Tensor

from morpheus_core.cameras import Cameras
from morpheus_core.geometry.mesh import Mesh
from morpheus_core.geometry.textured_mesh import BakedTexture
from morpheus_core.render.mesh_renderer import MeshRenderConfig, render_shaded
from morpheus_core.render.output import RenderOutput
from morpheus_core.render.raster import Fragments

_VALID = "a GLB/glTF or OBJ file with one textured triangle mesh (per-vertex UVs and a base colour texture image)"


class MeshLoadError(ValueError):
    """The asset file is missing, unreadable, or holds no triangle mesh with faces."""


class NoTextureError(MeshLoadError):
    """The mesh has no UVs or no base-colour image (e.g. vertex colours only), or several textures."""


@dataclass(frozen=True)
class TexturedMesh:
    """``vertices`` (V, 3) float32, ``faces`` (F, 3) int64, ``uvs`` (V, 2) float32 with v up, ``texture``
    (H, W, 3) float32 in [0, 1] with row 0 at v = 1 (``BakedTexture``'s layout, as float). Vertices are
    split along UV seams, so positions repeat there."""

    vertices: Tensor
    faces: Tensor
    uvs: Tensor
    texture: Tensor

    def __post_init__(self) -> None:
        if self.vertices.dim() != 2 or self.vertices.shape[-1] != 3:
            raise ValueError(f"vertices must be (V, 3), got {tuple(self.vertices.shape)}")
        if self.faces.dim() != 2 or self.faces.shape[-1] != 3 or self.faces.dtype != torch.int64:
            raise ValueError(f"faces must be (F, 3) int64, got {tuple(self.faces.shape)} {self.faces.dtype}")
        if self.uvs.shape != (self.vertices.shape[0], 2):
            raise ValueError(f"uvs must be ({self.vertices.shape[0]}, 2) (one per vertex), got {tuple(self.uvs.shape)}")
        if self.texture.dim() != 3 or self.texture.shape[-1] != 3 or min(self.texture.shape[:2]) < 1:
            raise ValueError(f"texture must be (H, W, 3), got {tuple(self.texture.shape)}")
        if not self.texture.is_floating_point():
            raise TypeError(f"texture must be floating point in [0, 1], got {self.texture.dtype}")

    @property
    def mesh(self) -> Mesh:
        return Mesh(self.vertices, self.faces)

    @property
    def device(self) -> torch.device:
        return self.vertices.device

    def to(self, device: torch.device | str) -> TexturedMesh:
        return TexturedMesh(self.vertices.to(device), self.faces.to(device), self.uvs.to(device),
                            self.texture.to(device))

    @classmethod
    def from_baked(cls, baked: BakedTexture) -> TexturedMesh:
        """The in-memory result of ``bake_uv``, without a round trip through a file (arrays are copied,
        so the two never share memory)."""
        return cls(
            vertices=torch.tensor(np.asarray(baked.vertices, dtype=np.float32)),
            faces=torch.tensor(np.asarray(baked.faces, dtype=np.int64)),
            uvs=torch.tensor(np.asarray(baked.uvs, dtype=np.float32)),
            texture=_image_to_float(np.array(baked.texture)),
        )

    def welded(self) -> tuple[Mesh, Tensor]:
        """The geometry with the seam copies merged — ``Mesh`` over the U distinct positions, faces in the
        same order — and ``weld`` (V,), each vertex's index among them.

        Rendering needs it: the rasteriser finds silhouette edges from the face topology, and a seam
        edge (two vertex copies per end) looks like an open boundary, so it would anti-alias pixels
        near the silhouette that the closed surface does not; area-weighted normals would also break
        at seams. Each merged position has exactly its copies' value, but its gradient goes in full to
        every copy, so optimised copies receive equal updates and stay together."""
        unique, weld = torch.unique(self.vertices.detach(), dim=0, return_inverse=True)
        summed = unique.new_zeros(unique.shape).index_add(0, weld, self.vertices)
        return Mesh(unique + (summed - summed.detach()), weld[self.faces]), weld


def _image_to_float(image: np.ndarray | Image.Image) -> Tensor:
    """(H, W, 3) float32 in [0, 1] from a PIL image or an RGB(A)/grey array (uint8, uint16 or float)."""
    if isinstance(image, Image.Image):
        if image.mode in ("I;16", "I;16B", "I;16L", "I"):
            # convert("RGB") would clip 16-bit grey to 255; scale through numpy instead.
            array = np.asarray(image, dtype=np.float64) / 65535.0
        else:
            array = np.asarray(image.convert("RGB"))
    else:
        array = np.asarray(image)
    if array.dtype == np.uint8:
        array = array.astype(np.float32) / 255.0
    elif array.dtype == np.uint16:
        array = array.astype(np.float32) / 65535.0
    array = np.asarray(array, dtype=np.float32)
    if array.ndim == 2:
        array = np.repeat(array[..., None], 3, axis=-1)
    if array.ndim != 3 or array.shape[-1] < 3:
        raise ValueError(f"texture image must be (H, W, 3|4) or (H, W), got {array.shape}")
    return torch.from_numpy(np.ascontiguousarray(array[..., :3])).clamp(0.0, 1.0)


def _base_colour_image(geometry: trimesh.Trimesh) -> Image.Image | np.ndarray | None:
    material = getattr(geometry.visual, "material", None)
    if material is None:
        return None
    # PBR (glTF) keeps the base colour in baseColorTexture; the simple (OBJ) material in image.
    image = getattr(material, "baseColorTexture", None)
    return image if image is not None else getattr(material, "image", None)


def load_textured(path: Path | str) -> TexturedMesh:
    """Load a GLB/glTF or OBJ asset holding one textured triangle mesh.

    Every triangle mesh of the file (scene transforms applied) is kept and concatenated; they must
    all carry UVs and share one base-colour image. Raises ``MeshLoadError`` when the file is missing,
    unreadable or has no faces, and ``NoTextureError`` when UVs or the image are missing (vertex
    colours only, untextured material) or when the meshes use different images."""
    path = Path(path)
    if not path.is_file():
        problem = "is not a file" if path.exists() else "no such file"
        raise MeshLoadError(f"{path}: {problem}; expected {_VALID}")
    try:
        # process=False keeps vertices split along UV seams (merging would weld them); maintain_order
        # keeps the OBJ's vertex order, so indices match the file.
        scene = trimesh.load_scene(path, process=False, maintain_order=True)
        geometries = scene.dump()
    except Exception as err:  # trimesh raises many types (ValueError, KeyError, struct.error, ...)
        raise MeshLoadError(f"{path}: could not be read as a mesh ({type(err).__name__}: {err}); "
                            f"expected {_VALID}") from err
    meshes = [g for g in geometries if isinstance(g, trimesh.Trimesh) and len(g.faces) > 0]
    if not meshes:
        kinds = sorted({type(g).__name__ for g in geometries}) or ["nothing"]
        raise MeshLoadError(f"{path}: contains no triangle mesh with faces (found {', '.join(kinds)}); "
                            f"expected {_VALID}")

    arrays: list[Tensor] = []
    for index, geometry in enumerate(meshes):
        uv = getattr(geometry.visual, "uv", None)
        image = _base_colour_image(geometry)
        if not isinstance(geometry.visual, trimesh.visual.TextureVisuals) or uv is None or image is None:
            what = ("vertex/face colours instead of a texture" if geometry.visual.kind in ("vertex", "face")
                    else "no UV coordinates" if uv is None else "no base colour texture image")
            raise NoTextureError(f"{path}: mesh {index} has {what}; expected {_VALID}")
        uv = np.asarray(uv)
        if uv.ndim != 2 or uv.shape[1] < 2 or len(uv) != len(geometry.vertices):
            raise NoTextureError(f"{path}: mesh {index} has UVs of shape {uv.shape} for {len(geometry.vertices)} "
                                 f"vertices (need one (u, v) per vertex); expected {_VALID}")
        texture = _image_to_float(image)
        if arrays and (texture.shape != arrays[0].shape or not torch.equal(texture, arrays[0])):
            raise NoTextureError(f"{path}: its meshes use {len(meshes)} different texture images, but only "
                                 f"single-texture assets are supported; bake the asset into one texture atlas "
                                 f"(expected {_VALID})")
        arrays.append(texture)

    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    vertices = np.concatenate([np.asarray(m.vertices) for m in meshes])
    faces = np.concatenate([np.asarray(m.faces, dtype=np.int64) + off for m, off in zip(meshes, offsets, strict=True)])
    uvs = np.concatenate([np.asarray(m.visual.uv)[:, :2] for m in meshes])
    if not (np.isfinite(vertices).all() and np.isfinite(uvs).all()):
        raise MeshLoadError(f"{path}: has non-finite vertex positions or UVs; expected {_VALID}")
    return TexturedMesh(
        vertices=torch.from_numpy(vertices.astype(np.float32)),
        faces=torch.from_numpy(faces),
        uvs=torch.from_numpy(uvs.astype(np.float32)),
        texture=arrays[0],
    )


def sample_texture(texture: Tensor, uv: Tensor) -> Tensor:
    """Bilinear lookup of ``texture`` (H, W, C) at ``uv`` (N, 2) → (N, C), clamped to the edge.

    v is up: u maps to column u·W − ½ and v to row (1 − v)·H − ½ (texel centres at integers), i.e.
    ``grid_sample`` with align_corners=False at x = 2u − 1, y = 1 − 2v. Differentiable w.r.t. both
    the texture and the UVs; computed in the wider of their two dtypes."""
    if texture.dim() != 3:
        raise ValueError(f"texture must be (H, W, C), got {tuple(texture.shape)}")
    if uv.dim() != 2 or uv.shape[-1] != 2:
        raise ValueError(f"uv must be (N, 2), got {tuple(uv.shape)}")
    dtype = torch.promote_types(texture.dtype, uv.dtype)
    if not dtype.is_floating_point:
        raise TypeError(f"texture and uv must be floating point, got {texture.dtype} and {uv.dtype}")
    image = texture.to(dtype).permute(2, 0, 1).unsqueeze(0)  # (1, C, H, W)
    uv = uv.to(device=texture.device, dtype=dtype)
    grid = torch.stack([uv[:, 0] * 2.0 - 1.0, 1.0 - uv[:, 1] * 2.0], dim=-1).view(1, 1, -1, 2)
    out = F.grid_sample(image, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return out[0, :, 0].transpose(0, 1)


def render_textured(mesh: TexturedMesh, cameras: Cameras, height: int, width: int,
                    background: float | Tensor = 1.0, config: MeshRenderConfig | None = None) -> RenderOutput:
    """Render ``mesh`` from every camera at ``height`` × ``width``: like ``render_mesh`` (same
    background compositing, anti-aliasing, depth and normal conventions) with each covered pixel
    coloured by the texture at its perspective-correct interpolated UV. Gradients reach the texture,
    the UVs and the vertices."""

    geometry, _ = mesh.welded()

    def shade(fragments: Fragments, _points: Tensor) -> Tensor:
        # Face ids are shared by the welded and the split faces; only the split ones index the UVs
        # (which differ between seam copies), so interpolate those with the fragments' barycentrics.
        device = fragments.clip.device
        corner_uvs = mesh.uvs.to(device)[mesh.faces.to(device)[fragments.face]]  # (N, 3, 2)
        uv = (fragments.bary.to(corner_uvs.dtype).unsqueeze(-1) * corner_uvs).sum(-2)
        return sample_texture(mesh.texture.to(device), uv)

    return render_shaded(geometry, cameras, height, width, shade, background=background, config=config,
                         shader_name="the texture lookup")


def sample_surface(mesh: TexturedMesh, count: int, generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
    """``count`` random points uniform over the surface (faces drawn by area, barycentrics by the
    square-root trick) and their texture colours: (count, 3) points and (count, 3) colours, on the
    mesh's device. The random draws happen on the generator's device (CPU without one)."""
    if count < 0:
        raise ValueError(f"count must be non-negative, got {count}")
    if mesh.faces.shape[0] == 0:
        raise ValueError("cannot sample the surface of a mesh without faces")
    if count == 0:
        empty = mesh.vertices.new_zeros(0, 3)
        return empty, empty.to(mesh.texture)
    corners = mesh.vertices[mesh.faces]  # (F, 3, 3)
    areas = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0], dim=-1).norm(dim=-1)
    if not bool(areas.sum() > 0):
        raise ValueError("cannot sample the surface of a mesh whose faces all have zero area")
    draw_device = generator.device if generator is not None else torch.device("cpu")
    face = torch.multinomial(areas.detach().to(draw_device, torch.float64), count, replacement=True,
                             generator=generator).to(mesh.device)
    r = torch.rand(count, 2, generator=generator, device=draw_device, dtype=torch.float64).to(mesh.device)
    # (1 − √r1, √r1(1 − r2), √r1·r2) is uniform over the triangle; plain uniform barycentrics are not.
    s = r[:, 0].sqrt()
    bary = torch.stack([1.0 - s, s * (1.0 - r[:, 1]), s * r[:, 1]], dim=-1).to(mesh.vertices.dtype)
    points = (bary.unsqueeze(-1) * corners[face]).sum(1)
    uv = (bary.to(mesh.uvs.dtype).unsqueeze(-1) * mesh.uvs[mesh.faces[face]]).sum(1)
    return points, sample_texture(mesh.texture, uv)
