"""Image-prompt encoders for the 2D prior, behind one interface.

The paper's 2D prior is Prompt-Free Diffusion, whose SeeCoder turns the reference photo into
the UNet's whole cross-attention context (no diffusers port exists). The default here is the
diffusers-native IP-Adapter: the context is the empty-prompt text embedding and the photo
enters through decoupled image cross-attention (``image_embeds``). A SeeCoder port implements
the same protocol with ``image_embeds = None`` and its tokens in ``context``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

import torch
from torch import Tensor, nn

from morpheus_core.imaging import batch_to_uint8_hwc
from morpheus_core.priors.runtime import PriorRuntime

IP_ADAPTER_WEIGHTS = ("models/ip-adapter_sd15.safetensors", "models/ip-adapter_sd15.bin")


@dataclass(frozen=True)
class PromptTokens:
    """What the UNet is conditioned on: ``context`` (B×L×D, also the ControlNet's) and, for
    IP-Adapter-style encoders, ``image_embeds`` (B×1×E) projected inside the UNet."""

    context: Tensor
    image_embeds: Tensor | None = None

    def cat(self, other: PromptTokens) -> PromptTokens:
        embeds = None if self.image_embeds is None else torch.cat([self.image_embeds, other.image_embeds])
        return PromptTokens(torch.cat([self.context, other.context]), embeds)


def stack_tokens(rows: list[PromptTokens]) -> PromptTokens:
    context = torch.cat([r.context for r in rows])
    embeds = None if rows[0].image_embeds is None else torch.cat([r.image_embeds for r in rows])
    return PromptTokens(context, embeds)


@runtime_checkable
class ImagePromptEncoder(Protocol):
    """Turns reference photos into UNet conditioning; owns its unconditional (null) tokens."""

    def attach(self, unet: nn.Module) -> None:
        """Install what the UNet needs to read the tokens (IP-Adapter: image attention layers)."""

    def encode(self, images: Tensor) -> PromptTokens:
        """Reference photos B×3×H×W in [0, 1] on white → tokens (B rows)."""

    def unconditional(self, tokens: PromptTokens) -> PromptTokens:
        """The classifier-free-guidance null for these tokens (same shapes)."""


class IPAdapterEncoder:
    """IP-Adapter (SD1.5): CLIP vision embedding → 4 image tokens via the UNet's projection.

    The null branch zeroes the image tokens handed to the UNet (the CLIP image embedding), the
    convention IP-Adapter was trained with for classifier-free guidance; the text context stays
    the empty-prompt embedding in both branches.
    """

    def __init__(
        self,
        image_encoder: nn.Module,
        image_processor: object,
        null_context: Tensor,
        adapter_state: dict[str, dict[str, Tensor]],
        runtime: PriorRuntime | None = None,
    ) -> None:
        if set(adapter_state) != {"image_proj", "ip_adapter"}:
            raise ValueError(f"IP-Adapter state needs 'image_proj' and 'ip_adapter' parts, got {sorted(adapter_state)}")
        self.runtime = runtime or PriorRuntime()
        self.image_encoder = self.runtime.place(image_encoder)
        self.image_processor = image_processor
        self.null_context = null_context.to(device=self.runtime.torch_device, dtype=self.runtime.dtype)
        self.adapter_state = adapter_state

    @classmethod
    def from_folders(cls, ip_folder: Path, sd_folder: Path, runtime: PriorRuntime | None = None) -> IPAdapterEncoder:
        """Offline load: the adapter file and CLIP encoder from ``ip_folder``, the empty-prompt
        context from the SD1.5 text encoder in ``sd_folder`` (computed once, encoder dropped)."""
        from transformers import CLIPImageProcessor, CLIPTextModel, CLIPTokenizer, CLIPVisionModelWithProjection

        ip_folder, sd_folder = Path(ip_folder), Path(sd_folder)
        enc_folder = ip_folder / "models" / "image_encoder"
        image_encoder = CLIPVisionModelWithProjection.from_pretrained(enc_folder, local_files_only=True)
        # The IP-Adapter release ships no preprocessor config: CLIP's normalisation at the
        # encoder's own input size (224 for its ViT-H/14, i.e. the library defaults).
        if (enc_folder / "preprocessor_config.json").is_file():
            processor = CLIPImageProcessor.from_pretrained(enc_folder, local_files_only=True)
        else:
            side = image_encoder.config.image_size
            processor = CLIPImageProcessor(size={"shortest_edge": side}, crop_size={"height": side, "width": side})
        tokenizer = CLIPTokenizer.from_pretrained(sd_folder / "tokenizer", local_files_only=True)
        text_encoder = CLIPTextModel.from_pretrained(sd_folder / "text_encoder", local_files_only=True)
        ids = tokenizer("", padding="max_length", max_length=tokenizer.model_max_length, truncation=True,
                        return_tensors="pt").input_ids
        with torch.no_grad():
            null_context = text_encoder(ids).last_hidden_state
        return cls(image_encoder, processor, null_context, load_ip_adapter_state(ip_folder), runtime)

    def attach(self, unet: nn.Module) -> None:
        # diffusers' pipeline-level ``load_ip_adapter`` reads the same file and ends in this UNet
        # method; calling it directly avoids building a text-to-image pipeline just to load.
        # The caller places the UNet (device, dtype) afterwards, new layers included.
        unet._load_ip_adapter_weights([self.adapter_state])

    def encode(self, images: Tensor) -> PromptTokens:
        dev, dt = self.runtime.torch_device, self.runtime.dtype
        with torch.no_grad():
            pixels = self.image_processor(images=batch_to_uint8_hwc(images), return_tensors="pt").pixel_values
            embeds = self.image_encoder(pixel_values=pixels.to(device=dev, dtype=dt)).image_embeds
        context = self.null_context.expand(embeds.shape[0], -1, -1)
        return PromptTokens(context, embeds[:, None].to(dt))

    def unconditional(self, tokens: PromptTokens) -> PromptTokens:
        return PromptTokens(tokens.context, torch.zeros_like(tokens.image_embeds))


def load_ip_adapter_state(ip_folder: Path) -> dict[str, dict[str, Tensor]]:
    """Read ``models/ip-adapter_sd15.{safetensors,bin}`` into its two parts (the release format:
    ``image_proj.*`` and ``ip_adapter.*`` keys in safetensors, nested dicts in the .bin)."""
    path = next((Path(ip_folder) / w for w in IP_ADAPTER_WEIGHTS if (Path(ip_folder) / w).is_file()), None)
    if path is None:
        raise FileNotFoundError(f"no {' or '.join(IP_ADAPTER_WEIGHTS)} in {ip_folder}")
    if path.suffix == ".bin":
        return torch.load(path, map_location="cpu", weights_only=True)
    from safetensors.torch import load_file

    state: dict[str, dict[str, Tensor]] = {"image_proj": {}, "ip_adapter": {}}
    for key, value in load_file(str(path)).items():
        part, _, rest = key.partition(".")
        if part not in state:
            raise KeyError(f"unexpected key {key!r} in {path}")
        state[part][rest] = value
    return state
