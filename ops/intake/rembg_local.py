"""rembg's U²-Net, run from a local .onnx file only: nothing here can reach the network.

rembg's own sessions resolve their model through a download helper (pooch) when the file is
absent or, for custom models, refuse paths outside rembg's home. We load the given file with
onnxruntime directly and reproduce rembg's U²-Net pre/post-processing (checked against rembg's
``U2netCustomSession`` in the tests): resize to 320² (Lanczos), divide by the image maximum,
ImageNet mean/std, first output's channel 0, min-max normalised, resized back (Lanczos).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from morpheus_core.priors.registry import rembg_model_candidates

INPUT_SIZE = 320
_MEAN = np.array([0.485, 0.456, 0.406])
_STD = np.array([0.229, 0.224, 0.225])


def model_candidates(configured: Path | None) -> tuple[Path, ...]:
    """Where to look: the configured file, or u2net.onnx in the configured folder, else under $U2NET_HOME."""
    if configured is None:
        return rembg_model_candidates("u2net")
    configured = Path(configured).expanduser()
    if configured.suffix == ".onnx":
        return (configured,)
    return configured / "u2net.onnx", configured / "models" / "u2net" / "u2net.onnx"


def find_model(configured: Path | None) -> Path | None:
    return next((p for p in model_candidates(configured) if p.is_file()), None)


class U2NetSession:
    """One onnxruntime session for a U²-Net .onnx file, created once and reused for every photo."""

    def __init__(self, model_path: Path, threads: int = 1) -> None:
        import onnxruntime as ort

        opts = ort.SessionOptions()
        # A batch runs one photo per worker process: more threads per session only oversubscribe cores.
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        opts.log_severity_level = 3
        self.model_path = Path(model_path)
        self._session = ort.InferenceSession(str(self.model_path), sess_options=opts,
                                             providers=["CPUExecutionProvider"])
        first = self._session.get_inputs()[0]
        if len(first.shape) != 4 or (isinstance(first.shape[1], int) and first.shape[1] != 3):
            raise ValueError(f"{self.model_path}: expected a 1×3×{INPUT_SIZE}×{INPUT_SIZE} input, got {first.shape}")
        self._input_name = first.name

    def predict(self, rgb: np.ndarray) -> np.ndarray:
        """Soft foreground alpha (H×W float32 in [0, 1]) for an H×W×3 float image in [0, 1]."""
        h, w = rgb.shape[:2]
        pil = Image.fromarray((np.clip(rgb, 0, 1) * 255).round().astype(np.uint8))
        x = np.asarray(pil.resize((INPUT_SIZE, INPUT_SIZE), Image.Resampling.LANCZOS), dtype=np.float64)
        x = (x / max(float(x.max()), 1e-6) - _MEAN) / _STD
        batch = x.transpose(2, 0, 1)[None].astype(np.float32)
        pred = np.asarray(self._session.run(None, {self._input_name: batch})[0], dtype=np.float64)
        pred = pred.reshape(pred.shape[0], -1, *pred.shape[-2:])[0, 0]
        lo, hi = float(pred.min()), float(pred.max())
        if not np.isfinite([lo, hi]).all() or hi - lo < 1e-12:
            return np.zeros((h, w), dtype=np.float32)  # a constant map holds no object (rembg would divide by 0)
        pred = (pred - lo) / (hi - lo)
        mask = Image.fromarray((pred.clip(0, 1) * 255).astype(np.uint8))
        return np.asarray(mask.resize((w, h), Image.Resampling.LANCZOS), dtype=np.float32) / 255.0
