"""The PNG previews people look at first: image strips, a stage's reference and turntable views, the mask overlay."""

from __future__ import annotations

import io
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch import Tensor

from assets_store.atomic import atomic_write_bytes
from morpheus_core.cameras import Cameras, turntable
from morpheus_core.render.output import RenderOutput
from ops.engine.target import ReferenceTarget, read_rgba

PREVIEW_FILE = "preview.png"


def to_uint8(image: Tensor) -> np.ndarray:
    """3×H×W (or 1×H×W) in [0, 1] → H×W×3 uint8."""
    img = image.detach().float().clamp(0, 1).cpu()
    if img.shape[0] == 1:
        img = img.expand(3, -1, -1)
    return (img.permute(1, 2, 0).numpy() * 255.0 + 0.5).astype(np.uint8)


def save_strip(path: Path, images: list[Tensor], size: int = 192) -> Path:
    """Side-by-side PNG of 3×H×W images, each resized to ``size`` (what people look at first)."""
    tiles = [F.interpolate(im[None].float().cpu(), size=(size, size), mode="bilinear", align_corners=False)[0]
             for im in images]
    strip = to_uint8(torch.cat(tiles, dim=-1))
    buf = io.BytesIO()
    Image.fromarray(strip).save(buf, format="PNG")
    return atomic_write_bytes(path, buf.getvalue())


def save_stage_preview(out_dir: Path, reference_dir: Path, render: Callable[[Cameras, int], RenderOutput],
                       size: int, device: torch.device) -> Path:
    """``preview.png``: photo | reference-view render | three views around the object."""
    photo = ReferenceTarget.load(reference_dir, size, device)
    with torch.no_grad():
        ref = render(photo.camera, size).rgb_chw()
        views = render(turntable(3, 15.0).to(device), size).rgb_chw()
    return save_strip(Path(out_dir) / PREVIEW_FILE, [photo.rgb[0], ref[0], *views], size)


def save_mask_overlay(out_dir: Path, reference_dir: Path, size: int = 160) -> Path:
    """``preview.png`` of the reference stage: the recentred photo | the mask over it (background
    tinted red), so a bad cut-out shows at a glance."""
    rgba = read_rgba(reference_dir, size)
    alpha = rgba[3:4]
    on_white = rgba[:3] * alpha + (1.0 - alpha)
    red = torch.tensor([0.9, 0.1, 0.1]).view(3, 1, 1)
    overlay = on_white * alpha + (0.5 * on_white + 0.5 * red) * (1.0 - alpha)
    return save_strip(Path(out_dir) / PREVIEW_FILE, [on_white, overlay], size)
