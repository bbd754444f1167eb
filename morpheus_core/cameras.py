"""Orbit cameras around the object: look-at, intrinsics, projection, rays, sampling, turntables.

Conventions shared by every renderer (NeRF and mesh renders must line up pixel for pixel):
- World: y up, right-handed; the object lives in [-1, 1]^3 and its front faces +z (glTF).
- Orbit position = d·(cos e·sin a, sin e, cos e·cos a): the reference camera (e = a = 0) sits on
  +z looking at the origin; positive elevation looks down from above.
- Camera frame: OpenGL (looks along its −z, +y up, +x right). Clip space: OpenGL perspective,
  NDC z in [−1, 1], w = −z_camera.
- Images: row 0 is the top. Pixel (i, j) has its centre at NDC x = (2j+1)/W − 1,
  y = 1 − (2i+1)/H.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from morpheus_core.runtime.devices import to_device
from morpheus_core.vectors import safe_normalize


@dataclass(frozen=True)
class OrbitConfig:
    """The paper's camera distribution: fov 40°, distance 2.5, elevation ±45°, azimuth ±180°."""

    fov_deg: float = 40.0
    distance: float = 2.5
    elevation_range: tuple[float, float] = (-45.0, 45.0)
    azimuth_range: tuple[float, float] = (-180.0, 180.0)
    near: float = 0.1
    far: float = 10.0

    def __post_init__(self) -> None:
        if not 0.0 < self.fov_deg < 180.0:
            raise ValueError(f"fov_deg must be in (0, 180), got {self.fov_deg}")
        if not 0.0 < self.near < self.far:
            raise ValueError(f"need 0 < near < far, got near={self.near}, far={self.far}")
        if self.distance <= self.near:
            raise ValueError(f"distance {self.distance} must exceed near {self.near}")
        for name, (lo, hi) in (("elevation_range", self.elevation_range), ("azimuth_range", self.azimuth_range)):
            if lo > hi:
                raise ValueError(f"{name} must be (low, high), got {(lo, hi)}")
        # |elevation| = 90° makes the look-at frame degenerate (view parallel to up).
        if max(abs(e) for e in self.elevation_range) >= 90.0:
            raise ValueError(f"elevation_range must stay inside (-90, 90), got {self.elevation_range}")


def look_at(eye: Tensor, target: Tensor, up: Tensor | None = None) -> Tensor:
    """(B, 4, 4) camera-to-world matrices for cameras at ``eye`` looking at ``target``."""
    eye, target = torch.broadcast_tensors(eye, target)
    if up is None:
        up = torch.tensor([0.0, 1.0, 0.0], dtype=eye.dtype, device=eye.device).expand_as(eye)
    back = safe_normalize(eye - target)  # camera +z points away from the target
    right = safe_normalize(torch.linalg.cross(up.expand_as(back), back, dim=-1))
    true_up = torch.linalg.cross(back, right, dim=-1)
    c2w = torch.zeros(*eye.shape[:-1], 4, 4, dtype=eye.dtype, device=eye.device)
    c2w[..., :3, 0] = right
    c2w[..., :3, 1] = true_up
    c2w[..., :3, 2] = back
    c2w[..., :3, 3] = eye
    c2w[..., 3, 3] = 1.0
    return c2w


def orbit_position(elevation_deg: Tensor, azimuth_deg: Tensor, distance: Tensor) -> Tensor:
    e, a = torch.deg2rad(elevation_deg), torch.deg2rad(azimuth_deg)
    return torch.stack(
        (distance * torch.cos(e) * torch.sin(a), distance * torch.sin(e), distance * torch.cos(e) * torch.cos(a)), -1
    )


@dataclass(frozen=True)
class Cameras:
    """A batch of B pinhole cameras (square pixels; ``fov_y`` is the vertical field of view)."""

    c2w: Tensor
    fov_y: Tensor
    elevation: Tensor
    azimuth: Tensor
    distance: Tensor
    near: float = 0.1
    far: float = 10.0

    def __post_init__(self) -> None:
        if self.c2w.dim() != 3 or self.c2w.shape[-2:] != (4, 4):
            raise ValueError(f"c2w must be (B, 4, 4), got {tuple(self.c2w.shape)}")
        b = self.c2w.shape[0]
        for name in ("fov_y", "elevation", "azimuth", "distance"):
            if getattr(self, name).shape != (b,):
                raise ValueError(f"{name} must be ({b},), got {tuple(getattr(self, name).shape)}")

    def __len__(self) -> int:
        return int(self.c2w.shape[0])

    def __getitem__(self, index: int | slice | Tensor) -> Cameras:
        if isinstance(index, int):
            index = slice(index, index + 1 if index != -1 else None)
        return Cameras(
            self.c2w[index], self.fov_y[index], self.elevation[index], self.azimuth[index], self.distance[index],
            self.near, self.far,
        )

    @classmethod
    def cat(cls, groups: Sequence[Cameras]) -> Cameras:
        """One batch of every camera of ``groups``, in order (all with the same near and far planes)."""
        if not groups:
            raise ValueError("Cameras.cat needs at least one batch of cameras")
        planes = {(g.near, g.far) for g in groups}
        if len(planes) > 1:
            raise ValueError(f"Cameras.cat needs one near/far pair, got {sorted(planes)}")
        return cls(*(torch.cat([getattr(g, name) for g in groups]) for name in
                     ("c2w", "fov_y", "elevation", "azimuth", "distance")), groups[0].near, groups[0].far)

    @property
    def device(self) -> torch.device:
        return self.c2w.device

    @property
    def dtype(self) -> torch.dtype:
        return self.c2w.dtype

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Cameras:
        def move(t: Tensor) -> Tensor:
            return to_device(t, device, dtype)

        return Cameras(
            move(self.c2w), move(self.fov_y), move(self.elevation), move(self.azimuth), move(self.distance),
            self.near, self.far,
        )

    @property
    def positions(self) -> Tensor:
        return self.c2w[:, :3, 3]

    def world_to_camera(self) -> Tensor:
        # The rotation block is orthonormal: invert it by transposition (exact, no solver).
        rot_t = self.c2w[:, :3, :3].transpose(1, 2)
        w2c = torch.zeros_like(self.c2w)
        w2c[:, :3, :3] = rot_t
        w2c[:, :3, 3] = -(rot_t @ self.c2w[:, :3, 3:4]).squeeze(-1)
        w2c[:, 3, 3] = 1.0
        return w2c

    def projection(self, aspect: float = 1.0) -> Tensor:
        """(B, 4, 4) OpenGL perspective; ``aspect`` = width / height."""
        f = 1.0 / torch.tan(self.fov_y / 2)
        n, fa = self.near, self.far
        p = torch.zeros(len(self), 4, 4, dtype=self.dtype, device=self.device)
        p[:, 0, 0] = f / aspect
        p[:, 1, 1] = f
        p[:, 2, 2] = -(fa + n) / (fa - n)
        p[:, 2, 3] = -2.0 * fa * n / (fa - n)
        p[:, 3, 2] = -1.0
        return p

    def world_to_clip(self, aspect: float = 1.0) -> Tensor:
        return self.projection(aspect) @ self.world_to_camera()

    def intrinsics(self, height: int, width: int) -> Tensor:
        """(B, 3, 3) pixel-space K for an image whose v axis points down (row 0 at the top)."""
        focal = 0.5 * height / torch.tan(self.fov_y / 2)
        k = torch.zeros(len(self), 3, 3, dtype=self.dtype, device=self.device)
        k[:, 0, 0] = focal
        k[:, 1, 1] = focal
        k[:, 0, 2] = width / 2
        k[:, 1, 2] = height / 2
        k[:, 2, 2] = 1.0
        return k

    def rays(self, height: int, width: int) -> tuple[Tensor, Tensor]:
        """World-space ray origins and unit directions through every pixel centre, (B, H, W, 3)."""
        opts = {"dtype": self.dtype, "device": self.device}
        x = (2 * torch.arange(width, **opts) + 1) / width - 1
        y = 1 - (2 * torch.arange(height, **opts) + 1) / height
        tan_half = torch.tan(self.fov_y / 2).reshape(-1, 1, 1)
        aspect = width / height
        dx = (x.reshape(1, 1, -1) * tan_half * aspect).expand(-1, height, -1)
        dy = (y.reshape(1, -1, 1) * tan_half).expand(-1, -1, width)
        d_cam = torch.stack((dx, dy, -torch.ones_like(dx)), -1)
        dirs = safe_normalize(torch.einsum("bij,bhwj->bhwi", self.c2w[:, :3, :3], d_cam))
        origins = self.positions.reshape(-1, 1, 1, 3).expand_as(dirs)
        return origins, dirs


def _as_batch(value: Tensor | float | list[float], like: Tensor | None = None) -> Tensor:
    t = torch.as_tensor(value, dtype=torch.float32 if like is None else like.dtype)
    return t.reshape(-1) if like is None else t.to(like.device).reshape(-1)


def orbit(
    elevation_deg: Tensor | float | list[float],
    azimuth_deg: Tensor | float | list[float],
    distance: Tensor | float | list[float] = 2.5,
    fov_deg: Tensor | float | list[float] = 40.0,
    near: float = 0.1,
    far: float = 10.0,
) -> Cameras:
    """Cameras on the orbit, broadcasting scalars against the batch of angles."""
    e = _as_batch(elevation_deg)
    a, d, f = (_as_batch(v, e) for v in (azimuth_deg, distance, fov_deg))
    e, a, d, f = torch.broadcast_tensors(e, a, d, f)
    eye = orbit_position(e, a, d)
    c2w = look_at(eye, torch.zeros_like(eye))
    return Cameras(c2w, torch.deg2rad(f), e.clone(), a.clone(), d.clone(), near, far)


def reference_camera(config: OrbitConfig | None = None) -> Cameras:
    config = config or OrbitConfig()
    return orbit(0.0, 0.0, config.distance, config.fov_deg, config.near, config.far)


def sample_orbit(n: int, config: OrbitConfig | None = None, generator: torch.Generator | None = None) -> Cameras:
    """``n`` cameras with elevation and azimuth uniform in the configured ranges (seeded)."""
    config = config or OrbitConfig()
    u = torch.rand(2, n, generator=generator, dtype=torch.float64)
    (elo, ehi), (alo, ahi) = config.elevation_range, config.azimuth_range
    elev = (elo + (ehi - elo) * u[0]).float()
    azim = (alo + (ahi - alo) * u[1]).float()
    return orbit(elev, azim, config.distance, config.fov_deg, config.near, config.far)


def turntable(n: int, elevation_deg: float = 0.0, config: OrbitConfig | None = None) -> Cameras:
    """``n`` evenly spaced azimuths starting at the reference view (0°), wrapped into (−180°, 180°]."""
    config = config or OrbitConfig()
    if n < 1:
        raise ValueError(f"a turntable needs at least one view, got n={n}")
    azim = torch.arange(n, dtype=torch.float64) * (360.0 / n)
    azim = torch.where(azim > 180.0, azim - 360.0, azim).float()
    return orbit(elevation_deg, azim, config.distance, config.fov_deg, config.near, config.far)


def fov_half_extent(fov_deg: float, distance: float) -> float:
    """Half the height of the view frustum at the orbit centre: what fits in the frame."""
    return distance * math.tan(math.radians(fov_deg) / 2)
