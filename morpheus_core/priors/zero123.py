"""Zero-1-to-3 (XL) as the 3D prior: ε(x_t, t | reference image, relative camera).

Conditioning (the released model's convention):
- the reference photo is composited on white at 256 px;
- cross-attention input: CLIP image embedding (1×768) concatenated with the relative camera
  [Δpolar (rad), sin Δazimuth, cos Δazimuth, Δradius] and projected 772 → 768;
- the UNet's 8 input channels are the noisy latent (scaled by the VAE factor) and the reference
  latent, unscaled (``latent_dist.mode()``);
- classifier-free guidance: the unconditional branch is zeros for both the projected embedding
  and the reference latent.
Zero123 parametrises elevation by the polar angle θ = 90° − elevation, so Δpolar = −Δelevation.

The per-object reference conditioning (CLIP embedding, reference latent, reference camera) is
computed once by ``set_reference`` and gathered per batch row, so one call mixes objects.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from torch import Tensor, nn

from morpheus_core.guidance.diffusion import apply_cfg
from morpheus_core.imaging import batch_to_uint8_hwc, composite_batch_on_white, resize_batch
from morpheus_core.priors.objects import check_rows, gather_rows
from morpheus_core.priors.registry import ModelRegistry
from morpheus_core.priors.runtime import PriorRuntime
from morpheus_core.priors.vae import LatentCodec

if TYPE_CHECKING:
    from morpheus_core.priors.lora import ObjectLoras

ZERO123_RESOLUTION = 256
# The two public diffusers layouts of the camera projection: folder → weight-name prefix.
PROJECTION_LAYOUTS = {"cc_projection": "projection.", "clip_camera_projection": "proj."}


@dataclass(frozen=True)
class Camera:
    """A camera on the orbit: elevation above the horizon and azimuth in degrees, distance."""

    elevation_deg: float = 0.0
    azimuth_deg: float = 0.0
    radius: float = 2.5


@dataclass(frozen=True)
class Zero123Condition:
    """One step's views: the object of each row and its camera (tensors of shape B)."""

    object_ids: tuple[str, ...]
    elevation_deg: Tensor
    azimuth_deg: Tensor
    radius: Tensor


def relative_camera(elevation_deg: Tensor, azimuth_deg: Tensor, radius: Tensor, reference: Tensor) -> Tensor:
    """Zero123's camera vector per row, B×4: [Δpolar (rad), sin Δaz, cos Δaz, Δradius].

    ``reference`` is B×3 (elevation°, azimuth°, radius) of each row's reference view.
    """
    # Cameras may come from the CPU (samplers) while the cached reference lives on the prior's device.
    ref = reference.to(torch.float32)
    e, a, r = (x.to(device=ref.device, dtype=torch.float32).reshape(-1) for x in (elevation_deg, azimuth_deg, radius))
    d_polar = torch.deg2rad(ref[:, 0] - e)  # θ = 90° − elevation
    d_az = torch.deg2rad(a - ref[:, 1])
    return torch.stack([d_polar, torch.sin(d_az), torch.cos(d_az), r - ref[:, 2]], dim=-1)


class CameraProjection(nn.Module):
    """The 772 → 768 linear map from [CLIP embedding, camera vector] to the UNet's context."""

    def __init__(self, in_features: int, out_features: int) -> None:
        super().__init__()
        if in_features != out_features + 4:
            raise ValueError(f"camera projection must map embedding+4 → embedding, got {in_features}→{out_features}")
        self.linear = nn.Linear(in_features, out_features)

    def forward(self, x: Tensor) -> Tensor:
        return self.linear(x)

    @classmethod
    def from_folder(cls, model_folder: Path) -> CameraProjection:
        """Load either public layout: ``cc_projection/`` (``projection.*``) or
        ``clip_camera_projection/`` (``proj.*``); sizes come from the weights themselves."""
        for sub, prefix in PROJECTION_LAYOUTS.items():
            folder = Path(model_folder) / sub
            if (folder / "config.json").is_file():
                state = _load_state(folder)
                weight, bias = state.get(prefix + "weight"), state.get(prefix + "bias")
                if weight is None or bias is None:
                    raise KeyError(f"{folder} holds {sorted(state)}, expected {prefix}weight and {prefix}bias")
                proj = cls(weight.shape[1], weight.shape[0])
                proj.linear.load_state_dict({"weight": weight, "bias": bias})
                return proj
        raise FileNotFoundError(f"no {' or '.join(PROJECTION_LAYOUTS)} folder in {model_folder}")


def _load_state(folder: Path) -> dict[str, Tensor]:
    st = folder / "diffusion_pytorch_model.safetensors"
    if st.is_file():
        from safetensors.torch import load_file

        return load_file(str(st))
    return torch.load(folder / "diffusion_pytorch_model.bin", map_location="cpu", weights_only=True)


class Zero123Prior:
    """The Zero123 noise predictor behind the ``Prior`` protocol (latent space, 256 px)."""

    def __init__(
        self,
        unet: nn.Module,
        vae: nn.Module,
        image_encoder: nn.Module,
        image_processor: object,
        projection: CameraProjection,
        runtime: PriorRuntime | None = None,
        resolution: int = ZERO123_RESOLUTION,
    ) -> None:
        if unet.config.in_channels != 2 * unet.config.out_channels:
            raise ValueError(f"Zero123 UNet needs in_channels = 2 × latent channels, got {unet.config.in_channels}")
        self.runtime = runtime or PriorRuntime()
        self.unet = self.runtime.place(unet)
        self.codec = LatentCodec(vae, resolution, self.runtime)
        self.image_encoder = self.runtime.place(image_encoder)
        self.image_processor = image_processor
        self.projection = self.runtime.place(projection)
        self.resolution = resolution
        self._clip: dict[str, Tensor] = {}
        self._latents: dict[str, Tensor] = {}
        self._cameras: dict[str, Tensor] = {}
        self._frozen = self.runtime.accelerate(self._denoise)

    @classmethod
    def from_folder(cls, folder: Path, runtime: PriorRuntime | None = None) -> Zero123Prior:
        """Load a diffusers-layout Zero123 folder (offline: ``local_files_only``)."""
        from diffusers import AutoencoderKL, UNet2DConditionModel
        from transformers import CLIPImageProcessor, CLIPVisionModelWithProjection

        folder = Path(folder)
        return cls(
            UNet2DConditionModel.from_pretrained(folder / "unet", local_files_only=True),
            AutoencoderKL.from_pretrained(folder / "vae", local_files_only=True),
            CLIPVisionModelWithProjection.from_pretrained(folder / "image_encoder", local_files_only=True),
            CLIPImageProcessor.from_pretrained(folder / "feature_extractor", local_files_only=True),
            CameraProjection.from_folder(folder),
            runtime,
        )

    @classmethod
    def from_registry(cls, registry: ModelRegistry | None = None, runtime: PriorRuntime | None = None) -> Zero123Prior:
        """Raises ``ModelMissingError`` (listing the files) when the Zero123 folder is incomplete."""
        return cls.from_folder((registry or ModelRegistry()).require("zero123"), runtime)

    # -- Prior protocol -------------------------------------------------------------------------

    def encode(self, images: Tensor) -> Tensor:
        return self.codec.encode(images)

    def decode(self, latents: Tensor) -> Tensor:
        return self.codec.decode(latents)

    def predict_noise(
        self, noisy: Tensor, t: Tensor, condition: Zero123Condition, cfg_scale: float, lora: ObjectLoras | None = None
    ) -> Tensor:
        """CFG-combined ε for a batch mixing objects; ``lora`` adds each row's object adapter."""
        if not math.isfinite(cfg_scale):
            raise ValueError(f"cfg_scale must be finite, got {cfg_scale}")
        ids = check_rows(condition.object_ids, noisy.shape[0])
        dev, dt = self.runtime.torch_device, self.runtime.dtype
        ref_latents = gather_rows(self._latents, ids, "Zero123 reference")
        ref_cams = gather_rows(self._cameras, ids, "Zero123 reference")
        delta = relative_camera(condition.elevation_deg, condition.azimuth_deg, condition.radius, ref_cams)
        clip = gather_rows(self._clip, ids, "Zero123 reference")
        with torch.no_grad():
            context = self.projection(torch.cat([clip, delta.to(device=dev, dtype=dt)[:, None]], dim=-1))
        zt = noisy.to(device=dev, dtype=dt)
        t = t.to(dev)
        guided = cfg_scale != 1.0
        if guided:  # [unconditional; conditional] in one forward
            sample = torch.cat([torch.cat([zt, torch.zeros_like(ref_latents)], 1), torch.cat([zt, ref_latents], 1)])
            context = torch.cat([torch.zeros_like(context), context])
            t = torch.cat([t, t])
        else:
            sample = torch.cat([zt, ref_latents], 1)
        if self.runtime.channels_last:
            sample = sample.contiguous(memory_format=torch.channels_last)
        if lora is None:
            with torch.no_grad():
                eps = self._frozen(sample, t, context)
        else:
            eps = lora.denoise(self._denoise, (sample, t, context), ids + ids if guided else ids)
        eps = eps.float()
        if guided:
            eps_u, eps_c = eps.chunk(2)
            eps = apply_cfg(eps_u, eps_c, cfg_scale)
        return eps.to(noisy.dtype)

    # -- per-object reference conditioning ------------------------------------------------------

    def set_reference(self, object_id: str, image: Tensor, camera: Camera | None = None) -> None:
        """Cache the object's conditioning from its photo (3×H×W, or RGBA 4×H×W, in [0, 1])."""
        camera = camera or Camera()
        ref = resize_batch(composite_batch_on_white(image).float(), self.resolution)
        dev, dt = self.runtime.torch_device, self.runtime.dtype
        with torch.no_grad():
            pixels = self.image_processor(images=batch_to_uint8_hwc(ref), return_tensors="pt").pixel_values
            embeds = self.image_encoder(pixel_values=pixels.to(device=dev, dtype=dt)).image_embeds
            self._clip[object_id] = embeds[:, None].to(dt)  # 1×1×E
            self._latents[object_id] = self.codec.encode_unscaled(ref).to(dt)
        self._cameras[object_id] = torch.tensor(
            [[camera.elevation_deg, camera.azimuth_deg, camera.radius]], dtype=torch.float32, device=dev)

    def forget(self, object_id: str) -> None:
        for cache in (self._clip, self._latents, self._cameras):
            cache.pop(object_id, None)

    @property
    def object_ids(self) -> tuple[str, ...]:
        return tuple(self._clip)

    def condition(
        self, object_ids: Sequence[str], elevation_deg: Tensor, azimuth_deg: Tensor, radius: Tensor | None = None
    ) -> Zero123Condition:
        """This step's condition; ``radius`` defaults to each object's reference distance."""
        ids = tuple(object_ids)
        if radius is None:
            radius = gather_rows(self._cameras, ids, "Zero123 reference")[:, 2]
        return Zero123Condition(ids, elevation_deg, azimuth_deg, radius)

    # -- the network call -----------------------------------------------------------------------

    def _denoise(self, sample: Tensor, t: Tensor, context: Tensor) -> Tensor:
        return self.unet(sample, t, encoder_hidden_states=context).sample
