"""Write tiny random models in the public folder layouts the priors load (``save_pretrained``)."""

from __future__ import annotations

import json
from pathlib import Path

import torch
from safetensors.torch import save_file

from morpheus_core.metrics.lpips import LPIPS, LPIPS_FILE
from morpheus_core.metrics.weighted_models import MANIQA_FILE
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


# -- weighted QA metrics (morpheus_core/metrics/weighted.py) ---------------------------------------


def tiny_clip_vocab() -> dict[str, int]:
    """Every lowercase letter and '.' as a word-inner and a word-final BPE token, no merges: enough
    for CLIP's tokenizer to spell the CLIP-IQA prompts without unknown tokens."""
    vocab = {"<|startoftext|>": 0, "<|endoftext|>": 1}
    for ch in "abcdefghijklmnopqrstuvwxyz.":
        vocab[ch] = len(vocab)
        vocab[ch + "</w>"] = len(vocab)
    return vocab


def write_tiny_clip(folder: Path, seed: int = 0) -> Path:
    """A random ``CLIPModel`` (both towers), its image processor and tokenizer, as a CLIP snapshot."""
    from transformers import CLIPConfig, CLIPImageProcessor, CLIPModel, CLIPTokenizer

    folder.mkdir(parents=True, exist_ok=True)
    vocab = tiny_clip_vocab()
    (folder / "vocab.json").write_text(json.dumps(vocab))
    (folder / "merges.txt").write_text("#version: 0.2\n")
    CLIPTokenizer(str(folder / "vocab.json"), str(folder / "merges.txt"), model_max_length=77).save_pretrained(folder)
    CLIPImageProcessor(size={"shortest_edge": 32}, crop_size={"height": 32, "width": 32}).save_pretrained(folder)
    config = CLIPConfig(
        text_config=dict(vocab_size=len(vocab), hidden_size=32, intermediate_size=37, num_hidden_layers=2,
                         num_attention_heads=4, max_position_embeddings=77, bos_token_id=0, eos_token_id=1,
                         pad_token_id=1),
        vision_config=dict(hidden_size=32, intermediate_size=37, num_hidden_layers=2, num_attention_heads=4,
                           image_size=32, patch_size=8),
        projection_dim=16,
    )
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = CLIPModel(config)
    model.save_pretrained(folder)
    return folder


def tiny_lpips(seed: int = 0, net: str = "alex") -> LPIPS:
    """LPIPS with the real trunk layout (kernels, strides, key indices) but narrow random layers; the
    heads are non-negative like the trained ones, so distances are ≥ 0."""
    channels = (8, 12, 16, 12, 12) if net == "alex" else (4, 4, 6, 6, 8, 8, 8, 8, 8, 8, 8, 8, 8)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = LPIPS(net, channels)
        with torch.no_grad():
            for lin in model.lin:
                lin.weight.abs_()
    return model


def write_tiny_maniqa(path: Path, fixed_batch: int | None = None, seed: int = 0, channels: int = 3) -> Path:
    """A MANIQA stand-in with the documented ONNX contract (N×3×224×224 → N×1), built with onnx.helper:
    patchify conv → ReLU → global average → linear → sigmoid, random weights. ``fixed_batch`` exports
    a static batch dimension (as a traced MANIQA at batch 1 has); ``channels`` ≠ 3 breaks the contract."""
    import numpy as np
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    rng = np.random.default_rng(seed)
    inits = {
        "conv_w": rng.normal(0.0, 0.05, (4, channels, 16, 16)).astype(np.float32),
        "conv_b": rng.normal(0.0, 0.05, (4,)).astype(np.float32),
        "fc_w": rng.normal(0.0, 1.0, (1, 4)).astype(np.float32),
        "fc_b": np.zeros((1,), np.float32),
    }
    nodes = [
        helper.make_node("Conv", ["image", "conv_w", "conv_b"], ["c"], strides=[16, 16]),
        helper.make_node("Relu", ["c"], ["r"]),
        helper.make_node("GlobalAveragePool", ["r"], ["p"]),
        helper.make_node("Flatten", ["p"], ["f"]),
        helper.make_node("Gemm", ["f", "fc_w", "fc_b"], ["g"], transB=1),
        helper.make_node("Sigmoid", ["g"], ["score"]),
    ]
    batch: int | str = fixed_batch if fixed_batch else "N"
    graph = helper.make_graph(
        nodes, "maniqa_standin",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [batch, channels, 224, 224])],
        [helper.make_tensor_value_info("score", TensorProto.FLOAT, [batch, 1])],
        initializer=[numpy_helper.from_array(v, k) for k, v in inits.items()],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], producer_name="morpheus3d-tests")
    model.ir_version = 8  # an IR version every onnxruntime of the last years reads
    onnx.checker.check_model(model)
    path.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(model, str(path))
    return path


def write_weighted_metric_models(root: Path, seed: int = 0) -> Path:
    """The default weighted-metric layout under ``root``: lpips/, clip/, maniqa/."""
    tiny_lpips(seed).save(root / "lpips" / LPIPS_FILE)
    write_tiny_clip(root / "clip", seed)
    write_tiny_maniqa(root / "maniqa" / MANIQA_FILE, seed=seed)
    return root
