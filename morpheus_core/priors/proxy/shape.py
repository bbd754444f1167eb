"""Inflated proxy object from one reference photo: the weight-free prior's stand-in for the real object.

When no diffusion weights are installed, the proxy prior pulls every novel view towards a render of
this proxy. It is built from the photo alone:

* **Geometry.** A world point p is projected through the reference camera (``OrbitConfig``: +z,
  distance 2.5, fov 40°) with the same ``world_to_clip`` the renderers use, giving image coordinates
  (u, v) (pixel centres at +0.5, row 0 at the top). D(u, v) is the signed Euclidean distance
  transform of the mask (alpha ≥ 0.5) in pixels, positive inside, zero on the pixel edges of the
  silhouette, sampled bilinearly; Dmax is its maximum and s the world size of one pixel at depth
  z = 0. The half-depth is H = thickness·s·sqrt(D·(2·Dmax − D)) inside (D > 0) and D·s outside, and
  the solid is |z| < H: its outline from the reference camera is exactly the mask, its
  cross-section is round (a disk silhouette with thickness 1 becomes a sphere in the reference
  camera's projective coordinates), the front is at z > 0 and the back at z < 0.
* **Colour.** Every point takes the photo colour at its reference-view projection — the front
  shows the photo, the back the same colour at the same image position, which seen from behind is
  the mirror image. The photo is first dilated ``colour_dilation`` px outward from the mask so
  points on the rim never pick up the white background.
* **Mesh.** Marching tetrahedra on a DMTet grid with a closed boundary, so a frame-filling
  silhouette (cut by the image border) is capped at the grid and the mesh stays closed
  (``priors.proxy.meshing``).

Image border: the distance transform does not treat the outside of the image as background
(OpenCV's convention), so an object cut by the frame keeps its depth up to the border, and beyond
the image the border values continue (``padding_mode="border"``) until the grid caps the shape.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch import Tensor

from morpheus_core.cameras import Cameras, OrbitConfig, reference_camera
from morpheus_core.export.uv_bake import dilate
from morpheus_core.geometry.mesh import Mesh
from morpheus_core.priors.proxy.meshing import build_mesh
from morpheus_core.render.mesh_renderer import render_mesh
from morpheus_core.render.output import RenderOutput

# Projections with clip w below this are behind (or at) the reference camera: not part of the shape.
_MIN_W = 1e-6


@dataclass(frozen=True)
class InflationConfig:
    """How the silhouette is inflated and meshed.

    ``thickness``: depth relative to a round profile (1.0 turns a disk silhouette into a sphere,
    0.5 into a lens half as deep). ``grid_resolution`` / ``half_extent``: the DMTet grid that meshes
    the shape, spanning [−half_extent, half_extent]³. ``colour_dilation``: pixels the photo colours
    are pushed outside the mask so side and rim points never sample the background.
    ``min_mask_pixels``: smaller masks are rejected as a failed segmentation.
    """

    thickness: float = 1.0
    grid_resolution: int = 64
    half_extent: float = 1.0
    colour_dilation: int = 16
    min_mask_pixels: int = 16

    def __post_init__(self) -> None:
        if not (math.isfinite(self.thickness) and self.thickness > 0):
            raise ValueError(f"thickness must be a positive finite number, got {self.thickness}")
        if isinstance(self.grid_resolution, bool) or not isinstance(self.grid_resolution, int) \
                or not 4 <= self.grid_resolution <= 1024:
            raise ValueError(f"grid_resolution must be an int in [4, 1024], got {self.grid_resolution!r}")
        if not (math.isfinite(self.half_extent) and self.half_extent > 0):
            raise ValueError(f"half_extent must be a positive finite number, got {self.half_extent}")
        if isinstance(self.colour_dilation, bool) or not isinstance(self.colour_dilation, int) \
                or self.colour_dilation < 0:
            raise ValueError(f"colour_dilation must be an int ≥ 0, got {self.colour_dilation!r}")
        if isinstance(self.min_mask_pixels, bool) or not isinstance(self.min_mask_pixels, int) \
                or self.min_mask_pixels < 1:
            raise ValueError(f"min_mask_pixels must be an int ≥ 1, got {self.min_mask_pixels!r}")


class EmptySilhouetteError(ValueError):
    """The reference mask gives no usable silhouette: empty, below ``min_mask_pixels``, or the whole image."""


def _as_rgba(image: Tensor | np.ndarray) -> Tensor:
    """(H, W, 4) float32 in [0, 1] on the input's device, from a float tensor/array or uint8."""
    if isinstance(image, np.ndarray):
        image = torch.from_numpy(np.array(image))  # a copy: PIL-backed arrays are read-only
    if not isinstance(image, Tensor):
        raise TypeError(f"reference image must be a torch tensor or numpy array, got {type(image).__name__}")
    if image.dim() != 3 or image.shape[-1] != 4 or image.shape[0] < 2 or image.shape[1] < 2:
        raise ValueError(f"reference image must be RGBA (H, W, 4) with H, W ≥ 2, got {tuple(image.shape)}")
    if image.dtype == torch.uint8:
        return image.float() / 255.0
    if not image.is_floating_point():
        raise TypeError(f"reference image must be uint8 or floating point in [0, 1], got {image.dtype}")
    image = image.float()
    if not bool(torch.isfinite(image).all()):
        raise ValueError("reference image holds NaN or ±inf values")
    lo, hi = float(image.min()), float(image.max())
    if lo < -1e-6 or hi > 1.0 + 1e-6:
        raise ValueError(f"float reference image must lie in [0, 1], got values in [{lo:.4g}, {hi:.4g}] "
                         "(pass uint8 for 0–255 images)")
    return image.clamp(0.0, 1.0)


def _signed_distance(mask: np.ndarray) -> np.ndarray:
    """Signed Euclidean distance in pixels from each pixel centre to the silhouette's pixel edges.

    Positive inside. The ±0.5 puts the zero of the bilinear interpolant exactly on the edge
    between an inside and an outside pixel, so the reference-view outline is the mask itself.
    """
    inside = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    outside = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return np.where(mask, inside - 0.5, 0.5 - outside).astype(np.float32)


class InflatedProxy:
    """A closed, photo-textured proxy inflated from the silhouette of an RGBA reference image.

    ``rgba``: (H, W, 4) torch float in [0, 1] or numpy uint8, seen by the reference camera of
    ``orbit``. Tensors derived from it live on its device (CPU for numpy input); ``sdf``,
    ``colour`` and ``render`` follow the device of their inputs. Raises ``EmptySilhouetteError``
    when the mask is empty, smaller than ``min_mask_pixels`` or covers the whole image.
    """

    def __init__(self, rgba: Tensor | np.ndarray, config: InflationConfig | None = None,
                 orbit: OrbitConfig | None = None) -> None:
        self.config = config or InflationConfig()
        self.orbit = orbit or OrbitConfig()
        if self.config.half_extent >= self.orbit.distance:
            raise ValueError(f"half_extent {self.config.half_extent} must be below the reference camera's distance "
                             f"{self.orbit.distance}: the grid has to lie in front of the camera")
        image = _as_rgba(rgba)
        self.device = image.device
        self.height, self.width = int(image.shape[0]), int(image.shape[1])

        mask = (image[..., 3] >= 0.5).cpu().numpy()
        count = int(mask.sum())
        if count == 0:
            raise EmptySilhouetteError("the reference photo's mask is empty (no pixel has alpha ≥ 0.5): check the "
                                       "segmentation / the prepared reference's alpha")
        if count < self.config.min_mask_pixels:
            raise EmptySilhouetteError(f"the reference photo's mask is too small: {count} pixel(s) with alpha ≥ 0.5, "
                                       f"fewer than min_mask_pixels={self.config.min_mask_pixels}; check the "
                                       "segmentation / the prepared reference")
        if count == mask.size:
            raise EmptySilhouetteError("the reference photo's mask covers the whole image, so there is no silhouette "
                                       "to inflate; check the segmentation / the prepared reference")
        self.mask_array = mask
        """(H, W) bool silhouette (alpha ≥ 0.5), numpy."""
        self.touches_border = bool(mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any())
        distance = _signed_distance(mask)
        self.distance_px = distance
        """(H, W) signed distance to the silhouette's edge in pixels, numpy."""
        self.dmax = float(distance.max())
        # World size of one pixel on the z = 0 plane (the vertical fov spans the image height).
        self.pixel_size = 2.0 * self.orbit.distance * math.tan(math.radians(self.orbit.fov_deg) / 2) / self.height

        mask_t = torch.from_numpy(mask).to(self.device)
        colours, _ = dilate(image[..., :3], mask_t, self.config.colour_dilation)
        # Channels-first single-image batches, the layout grid_sample reads.
        self._maps = {self.device: (torch.from_numpy(distance).to(self.device)[None, None],
                                    colours.permute(2, 0, 1).unsqueeze(0).contiguous())}
        cam = reference_camera(self.orbit).to(dtype=torch.float64)
        self._world_to_clip = cam.world_to_clip(aspect=self.width / self.height)[0]
        self._mesh: Mesh | None = None
        self._meshes: dict[torch.device, Mesh] = {}

    @property
    def mask(self) -> Tensor:
        """(H, W) bool silhouette (alpha ≥ 0.5) on the proxy's device."""
        return torch.from_numpy(self.mask_array).to(self.device)

    def _maps_on(self, device: torch.device, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
        if device not in self._maps:
            base_d, base_c = self._maps[self.device]
            self._maps[device] = (base_d.to(device), base_c.to(device))
        d, c = self._maps[device]
        return d.to(dtype), c.to(dtype)

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Reference-view projection of (N, 3) world points: (N, 2) grid_sample coordinates in
        [−1, 1] for pixel edges (x right, y down; = (ndc_x, −ndc_y)) and (N,) clip w (> 0 in front)."""
        if points.dim() != 2 or points.shape[-1] != 3:
            raise ValueError(f"points must be (N, 3), got {tuple(points.shape)}")
        if not points.is_floating_point():
            raise TypeError(f"points must be floating point, got {points.dtype}")
        m = self._world_to_clip.to(device=points.device, dtype=points.dtype)
        clip = points @ m[:3, :3].T + m[:3, 3]
        w = points @ m[3, :3] + m[3, 3]
        safe_w = torch.where(w > _MIN_W, w, torch.ones_like(w))
        ndc = clip[:, :2] / safe_w[:, None]
        return torch.stack((ndc[:, 0], -ndc[:, 1]), -1), w

    def pixel_coordinates(self, points: Tensor) -> Tensor:
        """(N, 2) reference-view image coordinates (u = column, v = row; pixel centres at +0.5)."""
        grid, _ = self.project(points)
        return torch.stack(((grid[:, 0] + 1) * self.width / 2, (grid[:, 1] + 1) * self.height / 2), -1)

    def _sample(self, image: Tensor, grid: Tensor) -> Tensor:
        out = F.grid_sample(image, grid.reshape(1, 1, -1, 2), mode="bilinear", padding_mode="border",
                            align_corners=False)
        return out[0, :, 0].T  # (N, C)

    def signed_distance_px(self, points: Tensor) -> Tensor:
        """(N,) D at the points' reference-view projections, in pixels (positive inside the mask)."""
        grid, w = self.project(points)
        dist, _ = self._maps_on(points.device, points.dtype)
        d = self._sample(dist, grid)[:, 0]
        # Behind the reference camera nothing is inside; give it the most outside value there is.
        return torch.where(w > _MIN_W, d, dist.min().expand_as(d))

    def height_at(self, points: Tensor) -> Tensor:
        """(N,) half-depth H in world units at the points' projections (negative outside the mask)."""
        d = self.signed_distance_px(points)
        s, t = self.pixel_size, self.config.thickness
        inside = t * s * torch.sqrt((d * (2 * self.dmax - d)).clamp_min(0.0))
        return torch.where(d > 0, inside, d * s)

    def sdf(self, points: Tensor) -> Tensor:
        """(N,) signed function of (N, 3) world points, negative inside the proxy, zero on its surface.

        Computed as sqrt((z/thickness)² + ((Dmax − D)·s)²) − Dmax·s, which has the sign of
        |z| − H at every point (so the same solid and surface) but, unlike |z| − H, a finite slope
        at the rim, where H grows like sqrt(D): marching tets places crossings by linear
        interpolation, and the infinite slope would push the rim up to a third of a cell outward.
        For a disk silhouette with thickness 1 it is the exact sphere distance in the reference
        camera's projective coordinates.
        """
        d = self.signed_distance_px(points)
        s = self.pixel_size
        z = points[:, 2] / self.config.thickness
        return torch.sqrt(z * z + ((self.dmax - d) * s) ** 2) - self.dmax * s

    def colour(self, points: Tensor) -> Tensor:
        """(N, 3) dilated photo RGB at the points' reference-view projections (front and back alike)."""
        grid, _ = self.project(points)
        _, colours = self._maps_on(points.device, points.dtype)
        return self._sample(colours, grid).clamp(0.0, 1.0)

    def mesh(self) -> Mesh:
        """The proxy's closed surface on the proxy's device (built on first use, cached, detached)."""
        if self._mesh is None:
            with torch.no_grad():
                self._mesh = build_mesh(self, self.config.grid_resolution, self.config.half_extent)
            self._meshes[self._mesh.vertices.device] = self._mesh
        return self._mesh

    def _mesh_on(self, device: torch.device) -> Mesh:
        base = self.mesh()
        if device not in self._meshes:
            self._meshes[device] = base.to(device)
        return self._meshes[device]

    def render(self, cameras: Cameras, height: int, width: int, background: float | Tensor = 1.0) -> RenderOutput:
        """Render the proxy (mesh + photo colours) from ``cameras`` on the cameras' device."""
        return render_mesh(self._mesh_on(cameras.device), cameras, height, width, self.colour, background)

    def target_images(self, cameras: Cameras, height: int, width: int) -> Tensor:
        """(B, 3, H, W) renders on white without gradient: the proxy prior's clean target per camera."""
        with torch.no_grad():
            return self.render(cameras, height, width).rgb_chw().contiguous()


def from_reference_folder(folder: Path, size: int = 256, config: InflationConfig | None = None) -> InflatedProxy:
    """The proxy of a prepared reference folder, from its ``rgba_{size}.png``."""
    path = Path(folder) / f"rgba_{size}.png"
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: run `morpheus3d prepare` on the photo first to write the "
                                "reference folder")
    with Image.open(path) as img:
        rgba = np.asarray(img.convert("RGBA"))
    return InflatedProxy(rgba, config)
