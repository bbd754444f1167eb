"""The models behind the weighted QA metrics (``morpheus_core.metrics.weighted``): the folder and files each
metric needs (``METRIC_SPECS``) and the wrappers that hold loaded models (``LoadedClip``, ``ManiqaOnnx``).

The MANIQA ONNX contract that ``ManiqaOnnx`` checks, and the export recipe for ``maniqa.onnx``, are in the
``morpheus_core.metrics.weighted`` docstring (the skip detail of a missing ``maniqa.onnx`` points there).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from morpheus_core.metrics.lpips import LPIPS_FILE
from morpheus_core.priors.registry import ModelSpec

MANIQA_FILE = "maniqa.onnx"
MANIQA_SIZE = 224
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

_CLIP_FILES: tuple[tuple[str, ...], ...] = (
    ("config.json",), ("model.safetensors", "pytorch_model.bin"), ("preprocessor_config.json",))
_CLIP_HOW_TO = ("copy a transformers CLIP snapshot (config, weights, preprocessor and tokenizer files), e.g. "
                "`hf download openai/clip-vit-base-patch16 --local-dir <folder>` on a machine with internet access")

METRIC_SPECS: tuple[ModelSpec, ...] = (
    ModelSpec(
        "lpips", "lpips", "LPIPS v0.1 distance, reference photo vs reference-view render (lower = closer)",
        ((LPIPS_FILE,),),
        "fetch torchvision's alexnet-owt-7be5be79.pth (download.pytorch.org/models/) and LPIPS' "
        "lpips/weights/v0.1/alex.pth (github.com/richzhang/PerceptualSimilarity) on a machine with internet "
        "access, then `python -m morpheus_core.metrics.lpips --trunk alexnet-owt-7be5be79.pth --lin alex.pth "
        f"--out <folder>/{LPIPS_FILE}`",
    ),
    ModelSpec("clip_similarity", "clip", "CLIP image-embedding similarity of the novel views to the reference",
              _CLIP_FILES, _CLIP_HOW_TO),
    ModelSpec("clipiqa", "clip", "CLIP-IQA no-reference quality of the views (antonym prompts)",
              (*_CLIP_FILES, ("tokenizer.json", "vocab.json")), _CLIP_HOW_TO),
    ModelSpec(
        "maniqa", "maniqa", "MANIQA no-reference quality of the views (ONNX on onnxruntime CPU)",
        ((MANIQA_FILE,),),
        f"export the MANIQA model to <folder>/{MANIQA_FILE} with torch.onnx.export as described in "
        "morpheus_core/metrics/weighted.py (input N×3×224×224 ImageNet-normalised, output N×1)",
    ),
)


@dataclass
class LoadedClip:
    """A loaded CLIP: the model, its image processor, and its tokenizer once a text-prompted metric needs it."""

    model: Any  # transformers.CLIPModel
    processor: Any  # transformers.CLIPImageProcessor
    tokenizer: Any | None = None


class ManiqaOnnx:
    """``maniqa.onnx`` on onnxruntime's CPU provider, checked against the documented contract."""

    def __init__(self, path: Path) -> None:
        import onnxruntime as ort  # lazily: only a configured MANIQA needs it

        self.path = Path(path)
        options = ort.SessionOptions()
        options.log_severity_level = 3  # errors only; a missing optional graph optimisation is not news
        self.session = ort.InferenceSession(str(self.path), sess_options=options, providers=["CPUExecutionProvider"])
        inputs, outputs = self.session.get_inputs(), self.session.get_outputs()
        if len(inputs) != 1 or len(outputs) < 1:
            raise ValueError(f"{self.path}: expected one input and one output, got {len(inputs)} and {len(outputs)}")
        inp = inputs[0]
        shape = list(inp.shape)
        channels_ok = len(shape) == 4 and (shape[1] == 3 or not isinstance(shape[1], int))
        if inp.type != "tensor(float)" or not channels_ok:
            raise ValueError(f"{self.path}: input {inp.name!r} is {inp.type} {shape}, expected float N×3×224×224")
        self.input_name = inp.name
        # Symbolic (named) dimensions come back as strings: batch free, size our default.
        self.fixed_batch = shape[0] if isinstance(shape[0], int) and shape[0] > 0 else None
        self.size = (shape[2] if isinstance(shape[2], int) else MANIQA_SIZE,
                     shape[3] if isinstance(shape[3], int) else MANIQA_SIZE)

    def preprocess(self, views: Tensor) -> np.ndarray:
        shrink = views.shape[-2] > self.size[0] or views.shape[-1] > self.size[1]
        x = F.interpolate(views, size=self.size, mode="bilinear", align_corners=False, antialias=shrink).clamp(0, 1)
        mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
        std = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
        return ((x - mean) / std).numpy().astype(np.float32)

    def scores(self, views: Tensor, batch_size: int) -> Tensor:
        x = self.preprocess(views)
        step = self.fixed_batch or batch_size
        out: list[np.ndarray] = []
        for start in range(0, len(x), step):
            chunk = x[start:start + step]
            n = len(chunk)
            if self.fixed_batch and n < self.fixed_batch:  # pad a fixed-batch model's last chunk, drop the padding
                chunk = np.concatenate([chunk, np.repeat(chunk[-1:], self.fixed_batch - n, axis=0)])
            y = np.asarray(self.session.run(None, {self.input_name: chunk})[0], dtype=np.float64)
            if y.size != len(chunk):
                raise ValueError(f"{self.path}: output of shape {y.shape} for {len(chunk)} images, expected N×1")
            out.append(y.reshape(-1)[:n])
        return torch.from_numpy(np.concatenate(out))
