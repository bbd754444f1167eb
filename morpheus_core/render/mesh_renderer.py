"""Render a triangle mesh with a colour field for a batch of cameras: the DMTet and texture stages' renderer.

Colour comes from a field queried at the interpolated world-space surface point of every covered
pixel (the texture field during optimisation, an analytic function in tests), so the same field
later bakes into the UV texture. Gradients reach the mesh vertices through the perspective-correct
barycentrics (inside the silhouette) and the edge-based anti-aliasing (at it), and reach the
colour field through its inputs and outputs. The output is the shared ``RenderOutput``, laid out like
the volume renderer's so NeRF and mesh stages feed the same losses.

``render_shaded`` is the shared pipeline behind ``render_mesh`` and ``render_textured``
(``morpheus_core.render.textured``): only how a covered pixel gets its colour differs.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Literal

import torch
from torch import Tensor

from morpheus_core.cameras import Cameras
from morpheus_core.geometry.mesh import Mesh
from morpheus_core.render.antialias import antialias
from morpheus_core.render.output import RenderOutput
from morpheus_core.render.raster import Fragments, RasterConfig, interpolate_sparse, rasterize
from morpheus_core.runtime.devices import filled_like
from morpheus_core.vectors import safe_normalize

ColourFn = Callable[[Tensor], Tensor]
# (fragments, world points (N, 3)) -> colours (N, 3); see ``render_shaded``.
Shader = Callable[[Fragments, Tensor], Tensor]


@dataclass(frozen=True)
class MeshRenderConfig:
    """``normals``: "vertex" interpolates area-weighted vertex normals (smooth shading), "face" uses
    the flat normal of the visible face. ``antialias`` switches the silhouette anti-aliasing (and
    with it the silhouette gradients) on or off."""

    raster: RasterConfig = field(default_factory=RasterConfig)
    normals: Literal["vertex", "face"] = "vertex"
    antialias: bool = True

    def __post_init__(self) -> None:
        if self.normals not in ("vertex", "face"):
            raise ValueError(f"normals must be 'vertex' or 'face', got {self.normals!r}")


def _background(background: float | Tensor, like: Tensor) -> Tensor:
    bg = filled_like(background, like)
    if bg.dim() == 0:
        bg = bg.expand(3)
    try:
        return torch.broadcast_to(bg, like.shape)
    except RuntimeError as err:
        raise ValueError(f"background must broadcast to {tuple(like.shape)}, got {tuple(bg.shape)}") from err


def render_mesh(mesh: Mesh, cameras: Cameras, height: int, width: int, colour_fn: ColourFn,
                background: float | Tensor = 1.0, config: MeshRenderConfig | None = None) -> RenderOutput:
    """Render ``mesh`` from every camera at ``height`` × ``width``.

    ``colour_fn(points (N, 3)) -> (N, 3)`` is called once with the world positions of all covered
    pixels of all views. ``background``: a scalar, an RGB triple, or anything broadcastable to
    (B, H, W, 3). Returns rgb composited over the background, anti-aliased opacity, depth as the
    Euclidean distance from the camera centre (the volume renderer's convention) and unit
    world-space normals; depth and normals are 0 on background pixels."""
    return render_shaded(mesh, cameras, height, width, lambda _frags, points: colour_fn(points),
                         background=background, config=config, shader_name="colour_fn")


def render_mesh_groups(mesh: Mesh, groups: Sequence[Cameras], height: int, width: int, colour_fn: ColourFn,
                       background: float | Tensor = 1.0, config: MeshRenderConfig | None = None) -> list[RenderOutput]:
    """``render_mesh`` for several batches of cameras at one size in one pass, an output per batch.

    The stages render their reference view and a step's novel views of the same mesh every step: one
    rasterisation, one ``colour_fn`` call and one anti-aliasing pass for both launch half the
    kernels of two renders (the DMTet and texture stages are launch-bound on CUDA). Views are
    independent, so each output equals its own ``render_mesh`` up to float rounding."""
    cameras = Cameras.cat([g.to(device=mesh.vertices.device) for g in groups])
    out = render_mesh(mesh, cameras, height, width, colour_fn, background, config)
    return out.split([len(g) for g in groups])


def render_shaded(mesh: Mesh, cameras: Cameras, height: int, width: int, shader: Shader,
                  background: float | Tensor = 1.0, config: MeshRenderConfig | None = None,
                  shader_name: str = "shader") -> RenderOutput:
    """The rasterise → shade → composite → anti-alias pipeline shared by ``render_mesh`` (colour from a
    field at world points) and ``render_textured`` (colour from a UV texture), so both give the same
    opacity, depth and normals, and silhouette gradients, for the same geometry.

    ``shader(fragments, points (N, 3)) -> (N, 3)`` colours the N covered pixels of all views, in
    ``fragments.pixel_index`` order; ``points`` are their interpolated world positions (the shader may
    interpolate further vertex attributes with ``interpolate_sparse(attr, fragments)``).
    ``shader_name`` names the callback in the error raised when it returns the wrong shape."""
    config = config or MeshRenderConfig()
    vertices = mesh.vertices
    if not vertices.is_floating_point():
        raise TypeError(f"mesh vertices must be floating point, got {vertices.dtype}")
    if vertices.dtype in (torch.float16, torch.bfloat16):
        # Half-precision positions cannot place a 512-px silhouette; render in float32.
        mesh = mesh.to(dtype=torch.float32)
        vertices = mesh.vertices
    cameras = cameras.to(device=vertices.device, dtype=vertices.dtype)
    homog = torch.cat([vertices, torch.ones_like(vertices[:, :1])], dim=-1)
    clip = torch.einsum("bij,vj->bvi", cameras.world_to_clip(aspect=width / height), homog)
    # The mesh's cached topology when its faces sit with its vertices (the stages' case): no host reads.
    faces = mesh.topology if mesh.faces.device == vertices.device else mesh.faces.to(vertices.device)
    frags = rasterize(clip, faces, height, width, config.raster)

    points = interpolate_sparse(vertices, frags)
    colours = shader(frags, points)
    if colours.shape != points.shape:
        raise ValueError(f"{shader_name} must map (N, 3) points to (N, 3) colours, got {tuple(colours.shape)}")
    if config.normals == "vertex":
        normals = safe_normalize(interpolate_sparse(mesh.vertex_normals(), frags))
    else:
        normals = mesh.face_normals()[frags.face]
    view = frags.pixel_index // (height * width)
    depth = (points - cameras.positions[view]).norm(dim=-1, keepdim=True)

    mask = frags.mask
    rgb = frags.scatter(colours.to(vertices.dtype))
    rgb = rgb + (1.0 - mask) * _background(background, rgb)
    if config.antialias:
        blended = antialias(torch.cat([rgb, mask], dim=-1), frags)
        rgb, opacity = blended[..., :3], blended[..., 3:]
    else:
        opacity = mask
    return RenderOutput(rgb=rgb, opacity=opacity, depth=frags.scatter(depth), normal=frags.scatter(normals))
