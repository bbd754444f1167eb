"""Where model weights live on disk. Always local: nothing here (or anywhere) downloads.

The root folder comes from ``$MORPHEUS_MODELS`` (default ``~/.cache/morpheus3d/models``); each
model has its own sub-folder in the layout its library saves with ``save_pretrained``.
``check_model`` says exactly which files are missing so a user knows what to copy where.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

DEFAULT_MODELS_ROOT = Path("~/.cache/morpheus3d/models")


@dataclass(frozen=True)
class ModelSpec:
    """A model folder: each entry of ``required`` lists alternatives, one of which must exist."""

    name: str
    folder: str
    purpose: str
    required: tuple[tuple[str, ...], ...]


_UNET = ("unet/diffusion_pytorch_model.safetensors", "unet/diffusion_pytorch_model.bin")
_VAE = ("vae/diffusion_pytorch_model.safetensors", "vae/diffusion_pytorch_model.bin")

MODEL_SPECS: tuple[ModelSpec, ...] = (
    ModelSpec(
        "zero123",
        "zero123-xl",
        "3D prior (Zero-1-to-3 XL, diffusers layout)",
        (
            ("unet/config.json",), _UNET, ("vae/config.json",), _VAE,
            ("image_encoder/config.json",), ("feature_extractor/preprocessor_config.json",),
            ("cc_projection/config.json", "clip_camera_projection/config.json"),
        ),
    ),
    ModelSpec(
        "sd15",
        "stable-diffusion-v1-5",
        "2D prior base (SD1.5 UNet + VAE)",
        (("unet/config.json",), _UNET, ("vae/config.json",), _VAE, ("scheduler/scheduler_config.json",)),
    ),
    ModelSpec(
        "controlnet_canny",
        "controlnet-canny",
        "2D prior edge control (ControlNet canny for SD1.5)",
        (("config.json",), ("diffusion_pytorch_model.safetensors", "diffusion_pytorch_model.bin")),
    ),
    ModelSpec(
        "ip_adapter",
        "ip-adapter",
        "2D prior image prompt (IP-Adapter SD1.5 + its CLIP image encoder)",
        (
            ("models/ip-adapter_sd15.safetensors", "models/ip-adapter_sd15.bin"),
            ("models/image_encoder/config.json",),
        ),
    ),
)


def models_root() -> tuple[Path, str]:
    """The configured root folder and where that setting came from."""
    env = os.environ.get("MORPHEUS_MODELS")
    if env:
        return Path(env).expanduser(), "$MORPHEUS_MODELS"
    return DEFAULT_MODELS_ROOT.expanduser(), "default"


def rembg_model_file(model: str = "u2net") -> Path:
    """rembg looks for ``<model>.onnx`` under ``$U2NET_HOME`` (default ``~/.u2net``)."""
    home = Path(os.environ.get("U2NET_HOME", "~/.u2net")).expanduser()
    return home / f"{model}.onnx"


def rembg_model_candidates(model: str = "u2net") -> tuple[Path, ...]:
    """Every place under ``$U2NET_HOME`` where rembg keeps an already-present model: the flat
    layout and the per-model folder (``models/<model>/``) of newer rembg releases."""
    flat = rembg_model_file(model)
    return flat, flat.parent / "models" / model / f"{model}.onnx"


@dataclass(frozen=True)
class ModelStatus:
    spec: ModelSpec
    path: Path
    missing: tuple[str, ...]

    @property
    def present(self) -> bool:
        return not self.missing


def check_model(spec: ModelSpec, root: Path | None = None) -> ModelStatus:
    folder = (root or models_root()[0]) / spec.folder
    missing = tuple(
        " or ".join(alts) for alts in spec.required if not any((folder / a).is_file() for a in alts)
    )
    return ModelStatus(spec, folder, missing)


def check_all(root: Path | None = None) -> list[ModelStatus]:
    return [check_model(spec, root) for spec in MODEL_SPECS]
