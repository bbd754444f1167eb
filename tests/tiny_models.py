"""Write tiny random models in the public folder layouts the priors load (``save_pretrained``)."""

from __future__ import annotations

import json
from pathlib import Path

import torch
from safetensors.torch import save_file

from morpheus_core.priors.architectures import Image2DParts, Zero123Parts, image2d_parts, zero123_parts
from morpheus_core.priors.zero123 import PROJECTION_LAYOUTS


def write_zero123(folder: Path, parts: Zero123Parts, layout: str = "cc_projection") -> Path:
    parts.unet.save_pretrained(folder / "unet")
    parts.vae.save_pretrained(folder / "vae")
    parts.image_encoder.save_pretrained(folder / "image_encoder")
    parts.image_processor.save_pretrained(folder / "feature_extractor")
    lin = parts.projection.linear
    proj = folder / layout
    proj.mkdir(parents=True)
    prefix = PROJECTION_LAYOUTS[layout]
    save_file({prefix + "weight": lin.weight.detach().contiguous(), prefix + "bias": lin.bias.detach().contiguous()},
              str(proj / "diffusion_pytorch_model.safetensors"))
    # The two public layouts name their sizes differently; the loader reads sizes from the weights.
    if layout == "cc_projection":
        config = {"_class_name": "CCProjection", "in_channel": lin.in_features, "out_channel": lin.out_features}
    else:
        config = {"_class_name": "CLIPCameraProjection", "embedding_dim": lin.out_features,
                  "additional_embeddings": lin.in_features - lin.out_features}
    (proj / "config.json").write_text(json.dumps(config))
    return folder


def _tiny_text_encoder(folder: Path) -> None:
    from transformers import CLIPTextConfig, CLIPTextModel, CLIPTokenizer

    vocab = {"<|startoftext|>": 0, "<|endoftext|>": 1, "a</w>": 2, "b</w>": 3, "a": 4, "b": 5}
    tok = folder / "tokenizer"  # vocab.json + merges.txt beside what save_pretrained writes, as in SD1.5
    tok.mkdir(parents=True, exist_ok=True)
    (tok / "vocab.json").write_text(json.dumps(vocab))
    (tok / "merges.txt").write_text("#version: 0.2\n")
    CLIPTokenizer(str(tok / "vocab.json"), str(tok / "merges.txt"), model_max_length=77).save_pretrained(tok)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(3)
        text = CLIPTextModel(CLIPTextConfig(vocab_size=len(vocab), hidden_size=32, intermediate_size=37,
                                            num_hidden_layers=2, num_attention_heads=4, max_position_embeddings=77,
                                            bos_token_id=0, eos_token_id=1, pad_token_id=1))
    text.save_pretrained(folder / "text_encoder")


def write_image2d(root: Path, parts: Image2DParts) -> tuple[Path, Path, Path]:
    """SD1.5-layout folder, ControlNet folder and IP-Adapter folder (release file names)."""
    sd, cn, ip = root / "stable-diffusion-v1-5", root / "controlnet-canny", root / "ip-adapter"
    parts.unet.save_pretrained(sd / "unet")
    parts.vae.save_pretrained(sd / "vae")
    _tiny_text_encoder(sd)
    parts.controlnet.save_pretrained(cn)
    parts.image_encoder.save_pretrained(ip / "models" / "image_encoder")
    flat = {f"{part}.{k}": v.contiguous() for part, d in parts.ip_adapter_state.items() for k, v in d.items()}
    save_file(flat, str(ip / "models" / "ip-adapter_sd15.safetensors"))
    return sd, cn, ip


def write_all(root: Path, seed: int = 0) -> Path:
    """The default registry layout under ``root`` plus ``zero123-alt`` in the other projection layout."""
    write_zero123(root / "zero123-xl", zero123_parts("tiny", seed), "cc_projection")
    write_zero123(root / "zero123-alt", zero123_parts("tiny", seed), "clip_camera_projection")
    write_image2d(root, image2d_parts("tiny", seed + 1))
    return root
