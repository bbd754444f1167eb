"""The priors' network architectures, built with random weights from configs written here.

``full`` is the real size (SD1.5 UNet, Zero123-XL UNet = SD1.5 with 8 input channels, canny
ControlNet, SD VAE, CLIP ViT-L/14 and ViT-H/14 vision towers, IP-Adapter projection): compute
does not depend on weight values, so the speed benchmark uses these without any download.
``tiny`` keeps every architectural feature (cross-attention, ControlNet residuals, an 8× VAE,
IP-Adapter layers) at a size the CPU tests can build, save and load in seconds. Nothing here
stands in for real weights: a prior built from these is random and says nothing about quality.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import torch
from torch import Tensor, nn

Scale = Literal["full", "tiny"]

_SD_DOWN = ("CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "DownBlock2D")
_SD_UP = ("UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D")
_TINY_DOWN = ("CrossAttnDownBlock2D", "DownBlock2D")
_TINY_UP = ("UpBlock2D", "CrossAttnUpBlock2D")


def unet_config(scale: Scale, in_channels: int = 4, sample_size: int = 64) -> dict[str, Any]:
    if scale == "full":
        return dict(sample_size=sample_size, in_channels=in_channels, out_channels=4, layers_per_block=2,
                    block_out_channels=(320, 640, 1280, 1280), down_block_types=_SD_DOWN, up_block_types=_SD_UP,
                    cross_attention_dim=768, attention_head_dim=8, norm_num_groups=32)
    return dict(sample_size=8, in_channels=in_channels, out_channels=4, layers_per_block=1,
                block_out_channels=(16, 32), down_block_types=_TINY_DOWN, up_block_types=_TINY_UP,
                cross_attention_dim=32, attention_head_dim=4, norm_num_groups=8)


def controlnet_config(scale: Scale) -> dict[str, Any]:
    if scale == "full":
        return dict(in_channels=4, layers_per_block=2, block_out_channels=(320, 640, 1280, 1280),
                    down_block_types=_SD_DOWN, cross_attention_dim=768, attention_head_dim=8, norm_num_groups=32,
                    conditioning_embedding_out_channels=(16, 32, 96, 256))
    # Three stride-2 stages in the control embedding: the 8× of the VAE, as at full size.
    return dict(in_channels=4, layers_per_block=1, block_out_channels=(16, 32), down_block_types=_TINY_DOWN,
                cross_attention_dim=32, attention_head_dim=4, norm_num_groups=8,
                conditioning_embedding_out_channels=(8, 8, 8, 16))


def vae_config(scale: Scale) -> dict[str, Any]:
    channels = (128, 256, 512, 512) if scale == "full" else (8, 8, 16, 16)
    return dict(in_channels=3, out_channels=3, latent_channels=4, block_out_channels=channels,
                down_block_types=("DownEncoderBlock2D",) * 4, up_block_types=("UpDecoderBlock2D",) * 4,
                layers_per_block=2 if scale == "full" else 1, norm_num_groups=32 if scale == "full" else 4,
                sample_size=512 if scale == "full" else 64, scaling_factor=0.18215)


def clip_vision_config(scale: Scale, tower: Literal["vit_l14", "vit_h14"]) -> dict[str, Any]:
    if scale == "tiny":  # different projection widths so a swapped encoder fails loudly
        return dict(hidden_size=32, intermediate_size=37, num_hidden_layers=2, num_attention_heads=4,
                    image_size=32, patch_size=8, projection_dim=32 if tower == "vit_l14" else 24)
    if tower == "vit_l14":  # Zero123's image encoder
        return dict(hidden_size=1024, intermediate_size=4096, num_hidden_layers=24, num_attention_heads=16,
                    image_size=224, patch_size=14, projection_dim=768)
    # IP-Adapter SD1.5's OpenCLIP ViT-H/14 image encoder
    return dict(hidden_size=1280, intermediate_size=5120, num_hidden_layers=32, num_attention_heads=16,
                image_size=224, patch_size=14, projection_dim=1024, hidden_act="gelu")


def image_processor(scale: Scale) -> Any:
    from transformers import CLIPImageProcessor

    if scale == "full":
        return CLIPImageProcessor()
    return CLIPImageProcessor(size={"shortest_edge": 32}, crop_size={"height": 32, "width": 32})


@dataclass
class Zero123Parts:
    unet: nn.Module
    vae: nn.Module
    image_encoder: nn.Module
    image_processor: Any
    projection: nn.Module


@dataclass
class Image2DParts:
    unet: nn.Module
    controlnet: nn.Module
    vae: nn.Module
    image_encoder: nn.Module
    image_processor: Any
    ip_adapter_state: dict[str, dict[str, Tensor]]


def _randomize_zero_init(module: nn.Module, std: float) -> None:
    """ControlNet's output convolutions start at zero (so training begins from SD); random
    weights there make its residuals visible, as in a trained ControlNet."""
    with torch.no_grad():
        for p in module.parameters():
            if not p.any():
                p.normal_(0.0, std)


def zero123_parts(scale: Scale, seed: int = 0) -> Zero123Parts:
    from diffusers import AutoencoderKL, UNet2DConditionModel
    from transformers import CLIPVisionConfig, CLIPVisionModelWithProjection

    from morpheus_core.priors.zero123 import CameraProjection

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        unet = UNet2DConditionModel(**unet_config(scale, in_channels=8, sample_size=32))
        vae = AutoencoderKL(**vae_config(scale))
        vision = CLIPVisionModelWithProjection(CLIPVisionConfig(**clip_vision_config(scale, "vit_l14")))
        embed = vision.config.projection_dim
        projection = CameraProjection(embed + 4, unet.config.cross_attention_dim)
    return Zero123Parts(unet, vae, vision, image_processor(scale), projection)


def random_ip_adapter_state(unet: nn.Module, image_embed_dim: int, seed: int = 0) -> dict[str, dict[str, Tensor]]:
    """A random IP-Adapter (SD1.5 format) for ``unet``: the 4-token image projection and one
    to_k_ip / to_v_ip pair per cross-attention layer, keyed 1, 3, 5, … in processor order."""
    g = torch.Generator().manual_seed(seed)  # CPU tensors (a state dict as read from a file)
    cross = unet.config.cross_attention_dim
    blocks = unet.config.block_out_channels
    image_proj = {
        "proj.weight": torch.randn(4 * cross, image_embed_dim, generator=g, device="cpu") * image_embed_dim ** -0.5,
        "proj.bias": torch.zeros(4 * cross, device="cpu"),
        "norm.weight": torch.ones(cross, device="cpu"),
        "norm.bias": torch.zeros(cross, device="cpu"),
    }
    ip_adapter: dict[str, Tensor] = {}
    key_id = 1
    for name in unet.attn_processors:
        if name.endswith("attn1.processor"):
            continue
        if name.startswith("mid_block"):
            hidden = blocks[-1]
        elif name.startswith("up_blocks"):
            hidden = list(reversed(blocks))[int(name[len("up_blocks.")])]
        else:
            hidden = blocks[int(name[len("down_blocks.")])]
        for proj in ("to_k_ip", "to_v_ip"):
            w = torch.randn(hidden, cross, generator=g, device="cpu")
            ip_adapter[f"{key_id}.{proj}.weight"] = w * cross**-0.5
        key_id += 2
    return {"image_proj": image_proj, "ip_adapter": ip_adapter}


def image2d_parts(scale: Scale, seed: int = 0) -> Image2DParts:
    from diffusers import AutoencoderKL, ControlNetModel, UNet2DConditionModel
    from transformers import CLIPVisionConfig, CLIPVisionModelWithProjection

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        unet = UNet2DConditionModel(**unet_config(scale))
        controlnet = ControlNetModel(**controlnet_config(scale))
        if scale == "tiny":
            _randomize_zero_init(controlnet, std=0.2)
        vae = AutoencoderKL(**vae_config(scale))
        vision = CLIPVisionModelWithProjection(CLIPVisionConfig(**clip_vision_config(scale, "vit_h14")))
    state = random_ip_adapter_state(unet, vision.config.projection_dim, seed)
    return Image2DParts(unet, controlnet, vae, vision, image_processor(scale), state)
