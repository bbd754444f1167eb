"""The image-prompt 2D prior: SD1.5 UNet + canny ControlNet + an image-prompt encoder (512 px).

ε(x_t, t | reference photo, Canny(render)): the ControlNet reads the Canny edges (150/250) of
the current render — the implicit camera control of the paper (section 4.3) — and its residuals
are added to the UNet's skip connections; the photo enters through the ``ImagePromptEncoder``
(IP-Adapter by default). CFG (2.0 in the paper) uses the encoder's null tokens for the
unconditional branch with the same control image.
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
from morpheus_core.imaging import CANNY_HIGH, CANNY_LOW, canny_edges, composite_batch_on_white, resize_batch
from morpheus_core.priors.image_prompt import ImagePromptEncoder, IPAdapterEncoder, PromptTokens, stack_tokens
from morpheus_core.priors.objects import check_rows
from morpheus_core.priors.registry import ModelRegistry
from morpheus_core.priors.runtime import PriorRuntime
from morpheus_core.priors.vae import LatentCodec

if TYPE_CHECKING:
    from morpheus_core.priors.lora import ObjectLoras

IMAGE2D_RESOLUTION = 512


@dataclass(frozen=True)
class Image2DSettings:
    resolution: int = IMAGE2D_RESOLUTION
    canny_low: int = CANNY_LOW
    canny_high: int = CANNY_HIGH
    controlnet_scale: float = 1.0


@dataclass(frozen=True)
class Image2DCondition:
    """One step's condition: each row's object and the edge control of its render (B×3×R×R)."""

    object_ids: tuple[str, ...]
    control: Tensor


class Image2DPrior:
    """The 2D prior behind the ``Prior`` protocol (latent space, 512 px)."""

    def __init__(
        self,
        unet: nn.Module,
        controlnet: nn.Module,
        vae: nn.Module,
        encoder: ImagePromptEncoder,
        runtime: PriorRuntime | None = None,
        settings: Image2DSettings | None = None,
    ) -> None:
        self.runtime = runtime or PriorRuntime()
        self.settings = settings or Image2DSettings()
        self.encoder = encoder
        encoder.attach(unet)  # before placing, so added layers get the same device and dtype
        self.unet = self.runtime.place(unet)
        self.controlnet = self.runtime.place(controlnet)
        self.codec = LatentCodec(vae, self.settings.resolution, self.runtime)
        self._tokens: dict[str, PromptTokens] = {}
        self._frozen = self.runtime.accelerate(self._denoise)

    @classmethod
    def from_folders(
        cls, sd_folder: Path, controlnet_folder: Path, ip_adapter_folder: Path,
        runtime: PriorRuntime | None = None, settings: Image2DSettings | None = None,
    ) -> Image2DPrior:
        """Offline load of SD1.5 (unet, vae), the canny ControlNet and the IP-Adapter encoder."""
        from diffusers import AutoencoderKL, ControlNetModel, UNet2DConditionModel

        sd_folder = Path(sd_folder)
        return cls(
            UNet2DConditionModel.from_pretrained(sd_folder / "unet", local_files_only=True),
            ControlNetModel.from_pretrained(controlnet_folder, local_files_only=True),
            AutoencoderKL.from_pretrained(sd_folder / "vae", local_files_only=True),
            IPAdapterEncoder.from_folders(ip_adapter_folder, sd_folder, runtime),
            runtime,
            settings,
        )

    @classmethod
    def from_registry(
        cls, registry: ModelRegistry | None = None, runtime: PriorRuntime | None = None,
        settings: Image2DSettings | None = None,
    ) -> Image2DPrior:
        """Raises ``ModelMissingError`` (listing the files) for the first incomplete folder."""
        reg = registry or ModelRegistry()
        return cls.from_folders(reg.require("sd15"), reg.require("controlnet_canny"), reg.require("ip_adapter"),
                                runtime, settings)

    # -- Prior protocol -------------------------------------------------------------------------

    def encode(self, images: Tensor) -> Tensor:
        return self.codec.encode(images)

    def decode(self, latents: Tensor) -> Tensor:
        return self.codec.decode(latents)

    def predict_noise(
        self, noisy: Tensor, t: Tensor, condition: Image2DCondition, cfg_scale: float, lora: ObjectLoras | None = None
    ) -> Tensor:
        """CFG-combined ε for a batch mixing objects; ``lora`` adds each row's object adapter."""
        if not math.isfinite(cfg_scale):
            raise ValueError(f"cfg_scale must be finite, got {cfg_scale}")
        ids = check_rows(condition.object_ids, noisy.shape[0])
        dev, dt = self.runtime.torch_device, self.runtime.dtype
        tokens = self.tokens(ids)
        control = condition.control.to(device=dev, dtype=dt)
        sample = noisy.to(device=dev, dtype=dt)
        t = t.to(dev)
        guided = cfg_scale != 1.0
        if guided:  # [unconditional; conditional] in one forward, same control image
            tokens = self.encoder.unconditional(tokens).cat(tokens)
            sample, control, t = torch.cat([sample, sample]), torch.cat([control, control]), torch.cat([t, t])
        if self.runtime.channels_last:
            sample = sample.contiguous(memory_format=torch.channels_last)
            control = control.contiguous(memory_format=torch.channels_last)
        args = (sample, t, control, tokens.context) + (() if tokens.image_embeds is None else (tokens.image_embeds,))
        if lora is None:
            with torch.no_grad():
                eps = self._frozen(*args)
        else:
            eps = lora.denoise(self._denoise, args, ids + ids if guided else ids)
        eps = eps.float()
        if guided:
            eps_u, eps_c = eps.chunk(2)
            eps = apply_cfg(eps_u, eps_c, cfg_scale)
        return eps.to(noisy.dtype)

    # -- per-object reference and per-step condition --------------------------------------------

    def set_reference(self, object_id: str, image: Tensor) -> None:
        """Cache the object's image-prompt tokens from its photo (3×H×W or RGBA, in [0, 1])."""
        ref = resize_batch(composite_batch_on_white(image).float(), self.settings.resolution)
        self._tokens[object_id] = self.encoder.encode(ref)

    def forget(self, object_id: str) -> None:
        self._tokens.pop(object_id, None)

    @property
    def object_ids(self) -> tuple[str, ...]:
        return tuple(self._tokens)

    def tokens(self, object_ids: Sequence[str]) -> PromptTokens:
        missing = [o for o in dict.fromkeys(object_ids) if o not in self._tokens]
        if missing:
            raise KeyError(f"no image prompt for objects {missing}; call set_reference(object_id, image) first")
        return stack_tokens([self._tokens[o] for o in object_ids])

    def condition(self, object_ids: Sequence[str], renders: Tensor) -> Image2DCondition:
        """This step's condition: Canny edges of the current renders at the prior's resolution."""
        s = self.settings
        ids = check_rows(object_ids, renders.shape[0])
        return Image2DCondition(ids, canny_edges(renders, s.resolution, s.canny_low, s.canny_high))

    # -- the network call -----------------------------------------------------------------------

    def _denoise(
        self, sample: Tensor, t: Tensor, control: Tensor, context: Tensor, image_embeds: Tensor | None = None
    ) -> Tensor:
        down, mid = self.controlnet(
            sample, t, encoder_hidden_states=context, controlnet_cond=control,
            conditioning_scale=self.settings.controlnet_scale, return_dict=False,
        )
        added = None if image_embeds is None else {"image_embeds": [image_embeds]}
        return self.unet(
            sample, t, encoder_hidden_states=context, added_cond_kwargs=added,
            down_block_additional_residuals=down, mid_block_additional_residual=mid,
        ).sample
