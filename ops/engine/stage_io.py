"""What the optimising stages share: the reference target, losses, saved fields, previews, results."""

from __future__ import annotations

import io
import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch import Tensor, nn

from assets_store.atomic import atomic_write, atomic_write_bytes
from assets_store.runlog import write_runlog
from morpheus_core.cameras import Cameras, OrbitConfig, reference_camera, sample_orbit, turntable
from morpheus_core.devices import pick_device  # noqa: F401 - the stages' import path
from morpheus_core.metrics.image import psnr
from morpheus_core.render.output import RenderOutput
from ops.config.tree import from_dict, to_dict
from ops.engine.loop import LoopResult
from ops.engine.priors import read_rgba

RUNLOG_FILE = "runlog.parquet"
PREVIEW_FILE = "preview.png"


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


def novel_cameras(n: int, generator: torch.Generator, device: torch.device,
                  orbit: OrbitConfig | None = None) -> Cameras:
    return sample_orbit(n, orbit, generator).to(device)


def reference_psnr(render_rgb: Tensor, target: ReferenceTarget) -> float:
    value = psnr(render_rgb.detach().float().clamp(0, 1), target.rgb.float())
    return value if math.isfinite(value) else 99.0


def save_module(path: Path, module: nn.Module, config: Any, extra: dict[str, Tensor] | None = None) -> Path:
    """A module's weights (+ ``extra`` tensors) as safetensors, with the config that rebuilds it in
    the header. safetensors is byte-for-byte reproducible (torch.save is not across processes),
    so equal weights give equal content hashes and downstream caches hold."""
    from safetensors.torch import save_file

    tensors = {f"state.{k}": v.detach().cpu().contiguous() for k, v in module.state_dict().items()}
    tensors.update({f"extra.{k}": v.detach().cpu().contiguous() for k, v in (extra or {}).items()})
    meta = {"config": json.dumps(to_dict(config), sort_keys=True)}
    return atomic_write(path, lambda tmp: save_file(tensors, str(tmp), metadata=meta))


def load_module(path: Path, cls: type, config_cls: type, device: torch.device
                ) -> tuple[nn.Module, Any, dict[str, Tensor]]:
    """Rebuild a module saved by ``save_module``; returns (module, config, extra tensors)."""
    from safetensors import safe_open
    from safetensors.torch import load_file

    if not Path(path).is_file():
        raise FileNotFoundError(f"{path} is missing: run the stage that writes it first")
    with safe_open(str(path), framework="pt") as fh:
        meta = fh.metadata() or {}
    if "config" not in meta:
        raise ValueError(f"{path} has no config header: not written by this pipeline")
    config = from_dict(config_cls, json.loads(meta["config"]))
    tensors = load_file(str(path))
    module = cls(config)
    module.load_state_dict({k[6:]: v for k, v in tensors.items() if k.startswith("state.")})
    return module.to(device), config, {k[6:]: v for k, v in tensors.items() if k.startswith("extra.")}


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


@dataclass
class StageResult:
    """What a stage reports back: metrics for the manifest, notes for people, the prior used."""

    metrics: dict[str, Any]
    prior: str
    device: str
    notes: list[str] = field(default_factory=list)


def loop_metrics(result: LoopResult) -> dict[str, Any]:
    last = result.history[-1] if result.history else {}
    out: dict[str, Any] = {"steps_run": result.steps_run, "resumed_from_step": result.resumed_from,
                           "loop_wall_s": round(result.wall_s, 3)}
    out.update({f"guard_{k}": v for k, v in result.guards.as_dict().items()})
    if "ref_psnr" in last:
        out["ref_psnr"] = last["ref_psnr"]
    return out


def write_log(out_dir: Path, result: LoopResult) -> None:
    write_runlog(Path(out_dir) / RUNLOG_FILE, result.history)


def require_finite_output(name: str, tensors: dict[str, Tensor]) -> None:
    """The last line of defence: an output with NaN/Inf is never written."""
    for key, t in tensors.items():
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            raise FloatingPointError(f"{name}: {key} holds NaN/Inf; refusing to write a broken output")
