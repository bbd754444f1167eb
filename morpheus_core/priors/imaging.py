"""Image preparation shared by the priors: white compositing, resizing, uint8 views, Canny edges."""

from __future__ import annotations

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

# Thresholds of the canny ControlNet control in the paper (section 4.3).
CANNY_LOW = 150
CANNY_HIGH = 250


def as_batch(images: Tensor) -> Tensor:
    """Accept C×H×W or B×C×H×W images with C ∈ {3, 4}, values in [0, 1]."""
    if images.dim() == 3:
        images = images.unsqueeze(0)
    if images.dim() != 4 or images.shape[1] not in (3, 4):
        raise ValueError(f"expected (B×)C×H×W images with 3 or 4 channels, got {tuple(images.shape)}")
    return images


def composite_on_white(images: Tensor) -> Tensor:
    """RGBA → RGB over a white background (both priors were trained on white-background objects)."""
    images = as_batch(images)
    if images.shape[1] == 3:
        return images
    rgb, alpha = images[:, :3], images[:, 3:4]
    return rgb * alpha + (1.0 - alpha)


def resize(images: Tensor, size: int) -> Tensor:
    """Differentiable square resize; antialiased when shrinking so renders do not alias."""
    if images.shape[-2:] == (size, size):
        return images
    shrink = images.shape[-1] > size or images.shape[-2] > size
    return F.interpolate(images, size=(size, size), mode="bilinear", align_corners=False, antialias=shrink)


def to_uint8_hwc(images: Tensor) -> list[np.ndarray]:
    """B×3×H×W in [0, 1] → B uint8 H×W×3 arrays (what OpenCV and the CLIP processors take)."""
    arr = (images.detach().float().clamp(0.0, 1.0) * 255.0).round().to(torch.uint8)
    return list(arr.permute(0, 2, 3, 1).cpu().numpy())


def canny_edges(renders: Tensor, size: int, low: int = CANNY_LOW, high: int = CANNY_HIGH) -> Tensor:
    """Canny edge maps of renders at ``size`` px as B×3×size×size in {0, 1} (the ControlNet input).

    Not differentiable (the control is a condition, like the camera); runs in OpenCV on the CPU.
    """
    renders = composite_on_white(renders)
    frames = to_uint8_hwc(resize(renders.detach().float(), size))
    edges = np.stack([cv2.Canny(np.ascontiguousarray(f), low, high) for f in frames])  # B×H×W, 0/255
    control = torch.from_numpy(edges).to(renders.device, torch.float32).div_(255.0)
    return control.unsqueeze(1).expand(-1, 3, -1, -1).contiguous()
