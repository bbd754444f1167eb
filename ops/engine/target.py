"""The photo as the optimising stages see it: the reference target at a render size, and views around it."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch import Tensor

from morpheus_core.cameras import Cameras, OrbitConfig, reference_camera, sample_orbit
from morpheus_core.metrics.image import psnr


def read_rgba(reference_dir: Path, size: int) -> Tensor:
    """The prepared reference's RGBA at ``size`` (4×S×S in [0, 1]); resized from the largest file."""
    path = Path(reference_dir) / f"rgba_{size}.png"
    if not path.is_file():
        candidates = sorted(Path(reference_dir).glob("rgba_*.png"), key=lambda p: int(p.stem.split("_")[1]))
        if not candidates:
            raise FileNotFoundError(f"{reference_dir}: no rgba_<size>.png; run `morpheus3d prepare` first")
        path = candidates[-1]
    img = Image.open(path).convert("RGBA")
    if img.size != (size, size):
        img = img.resize((size, size), Image.Resampling.LANCZOS)
    return torch.from_numpy(np.asarray(img, dtype=np.float32) / 255.0).permute(2, 0, 1).contiguous()


@dataclass(frozen=True)
class ReferenceTarget:
    """The photo at the render resolution: RGB on white (1×3×R×R), mask (1×1×R×R), its camera."""

    rgb: Tensor
    mask: Tensor
    camera: Cameras

    @classmethod
    def load(cls, reference_dir: Path, resolution: int, device: torch.device,
             orbit: OrbitConfig | None = None) -> ReferenceTarget:
        rgba = read_rgba(reference_dir, resolution).to(device)
        alpha = rgba[3:4]
        rgb = rgba[:3] * alpha + (1.0 - alpha)
        return cls(rgb[None], alpha[None], reference_camera(orbit).to(device))

    @property
    def resolution(self) -> int:
        return int(self.rgb.shape[-1])

    def resized(self, resolution: int) -> ReferenceTarget:
        """The same photo at another render size (a coarse render phase); the camera is unchanged."""
        if resolution == self.resolution:
            return self
        def resize(x: Tensor) -> Tensor:
            # Smaller: the mean of the pixels each coarse pixel covers, as a render at that size averages.
            if resolution < self.resolution:
                return F.adaptive_avg_pool2d(x, resolution)
            return F.interpolate(x, (resolution, resolution), mode="bilinear", align_corners=False).clamp(0.0, 1.0)

        return ReferenceTarget(resize(self.rgb), resize(self.mask), self.camera)


def novel_cameras(n: int, generator: torch.Generator, device: torch.device,
                  orbit: OrbitConfig | None = None) -> Cameras:
    return sample_orbit(n, orbit, generator).to(device)


def reference_psnr(render_rgb: Tensor, target: ReferenceTarget) -> float:
    value = psnr(render_rgb.detach().float().clamp(0, 1), target.rgb.float())
    return value if math.isfinite(value) else 99.0
