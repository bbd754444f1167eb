"""Where model weights live on disk. Always local: nothing here (or anywhere) downloads.

The root folder comes from the ``ModelRegistry`` config, else ``$MORPHEUS_MODELS``, else
``~/.cache/morpheus3d/models``; each model has its own sub-folder in the layout its library saves
with ``save_pretrained``. ``ModelRegistry.require`` raises ``ModelMissingError`` naming the folder,
the missing files and how to provide them, before any library gets a chance to reach the Hub.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

DEFAULT_MODELS_ROOT = Path("~/.cache/morpheus3d/models")

# Every loader also passes local_files_only=True; this covers anything that still asks the Hub
# (huggingface_hub reads it when first imported, so set it before diffusers/transformers load).
os.environ.setdefault("HF_HUB_OFFLINE", "1")


@dataclass(frozen=True)
class ModelSpec:
    """A model folder: each entry of ``required`` lists alternatives, one of which must exist."""

    name: str
    folder: str
    purpose: str
    required: tuple[tuple[str, ...], ...]
    how_to: str


def _weights(sub: str, diffusers: bool = True) -> tuple[str, ...]:
    names = ("diffusion_pytorch_model.safetensors", "diffusion_pytorch_model.bin") if diffusers else (
        "model.safetensors", "pytorch_model.bin")
    return tuple(f"{sub}/{n}" if sub else n for n in names)


_PROJECTION_LAYOUTS = ("cc_projection", "clip_camera_projection")

MODEL_SPECS: tuple[ModelSpec, ...] = (
    ModelSpec(
        "zero123",
        "zero123-xl",
        "3D prior (Zero-1-to-3 XL, diffusers layout)",
        (
            ("unet/config.json",), _weights("unet"), ("vae/config.json",), _weights("vae"),
            ("image_encoder/config.json",), _weights("image_encoder", diffusers=False),
            ("feature_extractor/preprocessor_config.json",),
            tuple(f"{d}/config.json" for d in _PROJECTION_LAYOUTS),
            tuple(w for d in _PROJECTION_LAYOUTS for w in _weights(d)),
        ),
        "copy a diffusers-format Zero-1-to-3 XL snapshot (unet/, vae/, image_encoder/, feature_extractor/ and "
        "cc_projection/ or clip_camera_projection/), e.g. `hf download bennyguo/zero123-xl-diffusers "
        "--local-dir <folder>` on a machine with internet access",
    ),
    ModelSpec(
        "sd15",
        "stable-diffusion-v1-5",
        "2D prior base (SD1.5 UNet, VAE, text encoder for the empty prompt)",
        (
            ("unet/config.json",), _weights("unet"), ("vae/config.json",), _weights("vae"),
            ("text_encoder/config.json",), _weights("text_encoder", diffusers=False),
            ("tokenizer/tokenizer.json", "tokenizer/vocab.json"),
        ),
        "copy a diffusers-format Stable Diffusion 1.5 snapshot (unet/, vae/, text_encoder/, tokenizer/), e.g. "
        "`hf download stable-diffusion-v1-5/stable-diffusion-v1-5 --local-dir <folder>`",
    ),
    ModelSpec(
        "controlnet_canny",
        "controlnet-canny",
        "2D prior edge control (ControlNet canny for SD1.5)",
        (("config.json",), _weights("")),
        "copy a diffusers-format SD1.5 canny ControlNet, e.g. `hf download lllyasviel/sd-controlnet-canny "
        "--local-dir <folder>`",
    ),
    ModelSpec(
        "ip_adapter",
        "ip-adapter",
        "2D prior image prompt (IP-Adapter SD1.5 + its CLIP image encoder)",
        (
            ("models/ip-adapter_sd15.safetensors", "models/ip-adapter_sd15.bin"),
            ("models/image_encoder/config.json",), _weights("models/image_encoder", diffusers=False),
        ),
        "copy models/ip-adapter_sd15.safetensors and models/image_encoder/ of the IP-Adapter release, e.g. "
        "`hf download h94/IP-Adapter --include 'models/ip-adapter_sd15.safetensors' 'models/image_encoder/*' "
        "--local-dir <folder>`",
    ),
)

# Which model folders each prior role needs (the roles of ``guidance_presets``).
PRIOR_MODELS: Mapping[str, tuple[str, ...]] = {
    "3d": ("zero123",),
    "2d": ("sd15", "controlnet_canny", "ip_adapter"),
}


class ModelMissingError(FileNotFoundError):
    """A model folder lacks files; the message says which, where, and how to provide them."""

    def __init__(self, spec: ModelSpec, folder: Path, missing: tuple[str, ...]) -> None:
        self.spec = spec
        self.folder = folder
        self.missing = missing
        lines = "\n".join(f"  - {m}" for m in missing)
        super().__init__(
            f"model {spec.name!r} ({spec.purpose}) is missing files in {folder}:\n{lines}\n"
            f"To provide it: {spec.how_to.replace('<folder>', str(folder))}. "
            "Weights are never downloaded at run time; set $MORPHEUS_MODELS to change the root folder."
        )


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


def models_root() -> tuple[Path, str]:
    """The root folder from the environment and where that setting came from."""
    env = os.environ.get("MORPHEUS_MODELS")
    if env:
        return Path(env).expanduser(), "$MORPHEUS_MODELS"
    return DEFAULT_MODELS_ROOT.expanduser(), "default"


def rembg_model_file(model: str = "u2net") -> Path:
    """rembg looks for ``<model>.onnx`` under ``$U2NET_HOME`` (default ``~/.u2net``)."""
    home = Path(os.environ.get("U2NET_HOME", "~/.u2net")).expanduser()
    return home / f"{model}.onnx"


def spec_named(specs: tuple[ModelSpec, ...] | list[ModelSpec], name: str, kind: str = "model") -> ModelSpec:
    """The spec called ``name``; ``KeyError`` listing the known names otherwise."""
    for spec in specs:
        if spec.name == name:
            return spec
    raise KeyError(f"unknown {kind} {name!r}; known: {[s.name for s in specs]}")


def _spec(name: str) -> ModelSpec:
    return spec_named(MODEL_SPECS, name)


@dataclass(frozen=True)
class ModelRegistry:
    """Typed model configuration: the root folder and optional per-model folders.

    ``root`` None means ``$MORPHEUS_MODELS`` or the default; ``folders`` maps a model name to a
    folder (absolute, or relative to the root) replacing its default sub-folder.
    """

    root: Path | None = None
    folders: Mapping[str, Path] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in self.folders:
            _spec(name)  # fail at configuration time on a typo, not at load time

    def resolved_root(self) -> tuple[Path, str]:
        if self.root is not None:
            return Path(self.root).expanduser(), "config"
        return models_root()

    def folder(self, name: str) -> Path:
        spec = _spec(name)
        root = self.resolved_root()[0]
        return root / Path(self.folders.get(name, spec.folder)).expanduser()

    def status(self, name: str) -> ModelStatus:
        spec = _spec(name)
        path = self.folder(name)
        missing = tuple(" or ".join(alts) for alts in spec.required if not any((path / a).is_file() for a in alts))
        return ModelStatus(spec, path, missing)

    def statuses(self) -> list[ModelStatus]:
        return [self.status(spec.name) for spec in MODEL_SPECS]

    def require(self, name: str) -> Path:
        """The model's folder, or ``ModelMissingError`` if any expected file is absent."""
        status = self.status(name)
        if not status.present:
            raise ModelMissingError(status.spec, status.path, status.missing)
        return status.path

    def prior_ready(self, role: str) -> bool:
        return all(self.status(name).present for name in PRIOR_MODELS[role])
