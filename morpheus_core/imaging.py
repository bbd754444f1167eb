"""Pure image maths, in one place for both layouts the pipeline uses.

- References (preparation): numpy arrays, images H×W×3 float32 in [0, 1], alpha H×W float32,
  masks H×W bool — resizing, mask statistics, recentring on white.
- Renders (priors): torch batches B×C×H×W in [0, 1] — the ``*_batch`` functions (differentiable
  white compositing and resizing) and the Canny control of the 2D prior.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from morpheus_core.guidance.frequency import high_frequency_ratio


def resize(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resize to (width, height): area averaging when shrinking (no aliasing), cubic when growing."""
    w, h = size
    shrinking = w * h < img.shape[0] * img.shape[1]
    out = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_CUBIC)
    return np.clip(out, 0.0, 1.0)


def fit_within(size: tuple[int, int], max_side: int) -> tuple[int, int]:
    """(width, height) scaled down so the longer side is at most ``max_side``."""
    w, h = size
    s = min(1.0, max_side / max(w, h))
    return max(1, round(w * s)), max(1, round(h * s))


def bbox(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """(x0, y0, x1, y1), end-exclusive, of the True pixels; None for an empty mask."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return None
    return int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1


def touched_borders(mask: np.ndarray, min_fraction: float = 0.01) -> list[str]:
    """Image sides along which more than ``min_fraction`` of the edge pixels are object."""
    sides = {"top": mask[0], "bottom": mask[-1], "left": mask[:, 0], "right": mask[:, -1]}
    return [name for name, edge in sides.items() if edge.mean() > min_fraction]


def composite_on_white(rgb: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    return rgb * alpha[..., None] + (1.0 - alpha[..., None])


@dataclass(frozen=True)
class Recentred:
    """A square reference: RGB already composited on white, alpha, and where the object sits."""

    rgb: np.ndarray
    alpha: np.ndarray
    object_box: tuple[int, int, int, int]  # (x0, y0, x1, y1) of the object inside the square

    def rgba_u8(self) -> np.ndarray:
        rgba = np.concatenate([self.rgb, self.alpha[..., None]], axis=-1)
        out = (np.clip(rgba, 0.0, 1.0) * 255.0).round().astype(np.uint8)
        out[out[..., 3] == 0, :3] = 255  # alpha that rounds to 0 is background: exactly white
        return out


def recentre(rgb: np.ndarray, alpha: np.ndarray, box: tuple[int, int, int, int], size: int,
             border_ratio: float) -> Recentred:
    """Crop to ``box``, scale so the longer side fills ``1 − 2·border_ratio`` of a ``size``² square,
    centre it and composite on white.

    Compositing happens before resampling so the white background, not the undefined colour of
    transparent pixels, bleeds into the anti-aliased edge.
    """
    if not 0.0 <= border_ratio < 0.5:
        raise ValueError(f"border_ratio must lie in [0, 0.5), got {border_ratio}")
    x0, y0, x1, y1 = box
    crop_a = alpha[y0:y1, x0:x1]
    crop_rgb = composite_on_white(rgb[y0:y1, x0:x1], crop_a)
    target = max(1, round(size * (1.0 - 2.0 * border_ratio)))
    scale = target / max(x1 - x0, y1 - y0)
    w, h = max(1, round((x1 - x0) * scale)), max(1, round((y1 - y0) * scale))
    ox, oy = (size - w) // 2, (size - h) // 2
    out_rgb = np.ones((size, size, 3), dtype=np.float32)
    out_a = np.zeros((size, size), dtype=np.float32)
    out_rgb[oy:oy + h, ox:ox + w] = resize(crop_rgb.astype(np.float32), (w, h))
    out_a[oy:oy + h, ox:ox + w] = resize(crop_a.astype(np.float32), (w, h))
    return Recentred(out_rgb, out_a, (ox, oy, ox + w, oy + h))


def object_high_frequency_ratio(rgb: np.ndarray, alpha: np.ndarray, cutoff: float, erode_px: int = 2,
                                window_sigma: float = 3.0) -> float:
    """Share of the object's own spectral energy above ``cutoff``·Nyquist (see ``high_frequency_ratio``).

    Measured on the object's interior only: the silhouette against white is a strong edge that
    would swamp the texture, so the mean-removed object is multiplied by a soft window (the
    eroded mask, blurred) before the spectrum is taken. A flat-coloured object then scores low
    whatever its outline; print, grain and stripes score high.
    """
    core = cv2.erode((alpha >= 0.5).astype(np.uint8), np.ones((2 * erode_px + 1,) * 2, np.uint8))
    window = cv2.GaussianBlur(core.astype(np.float32), (0, 0), window_sigma) * core
    if window.sum() < 1.0:
        return 0.0
    mean = (rgb * window[..., None]).sum(axis=(0, 1)) / window.sum()
    centred = (rgb - mean) * window[..., None]
    return high_frequency_ratio(torch.from_numpy(np.ascontiguousarray(centred, dtype=np.float32)).permute(2, 0, 1),
                                cutoff)


# -- torch batches of renders (the priors) ----------------------------------------------------

# Thresholds of the canny ControlNet control in the paper (section 4.3).
CANNY_LOW = 150
CANNY_HIGH = 250


def as_image_batch(images: Tensor) -> Tensor:
    """Accept C×H×W or B×C×H×W images with C ∈ {3, 4}, values in [0, 1]."""
    if images.dim() == 3:
        images = images.unsqueeze(0)
    if images.dim() != 4 or images.shape[1] not in (3, 4):
        raise ValueError(f"expected (B×)C×H×W images with 3 or 4 channels, got {tuple(images.shape)}")
    return images


def composite_batch_on_white(images: Tensor) -> Tensor:
    """RGBA → RGB over a white background (both priors were trained on white-background objects)."""
    images = as_image_batch(images)
    if images.shape[1] == 3:
        return images
    rgb, alpha = images[:, :3], images[:, 3:4]
    return rgb * alpha + (1.0 - alpha)


def resize_batch(images: Tensor, size: int) -> Tensor:
    """Differentiable square resize_batch; antialiased when shrinking so renders do not alias."""
    if images.shape[-2:] == (size, size):
        return images
    shrink = images.shape[-1] > size or images.shape[-2] > size
    return F.interpolate(images, size=(size, size), mode="bilinear", align_corners=False, antialias=shrink)


def batch_to_uint8_hwc(images: Tensor) -> list[np.ndarray]:
    """B×3×H×W in [0, 1] → B uint8 H×W×3 arrays (what OpenCV and the CLIP processors take)."""
    arr = (images.detach().float().clamp(0.0, 1.0) * 255.0).round().to(torch.uint8)
    return list(arr.permute(0, 2, 3, 1).cpu().numpy())


def canny_edges(renders: Tensor, size: int, low: int = CANNY_LOW, high: int = CANNY_HIGH) -> Tensor:
    """Canny edge maps of renders at ``size`` px as B×3×size×size in {0, 1} (the ControlNet input).

    Not differentiable (the control is a condition, like the camera); runs in OpenCV on the CPU.
    """
    renders = composite_batch_on_white(renders)
    frames = batch_to_uint8_hwc(resize_batch(renders.detach().float(), size))
    edges = np.stack([cv2.Canny(np.ascontiguousarray(f), low, high) for f in frames])  # B×H×W, 0/255
    control = torch.from_numpy(edges).to(renders.device, torch.float32).div_(255.0)
    return control.unsqueeze(1).expand(-1, 3, -1, -1).contiguous()
