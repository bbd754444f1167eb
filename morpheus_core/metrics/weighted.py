"""Learned ("weighted") QA metrics of an asset's renders, each loaded from a local model folder.

Metrics, their default folders under the models root and the files each folder must hold (as data:
``METRIC_SPECS`` in ``morpheus_core/metrics/weighted_models.py``, beside the model wrappers):

- ``lpips`` (lower = closer): LPIPS v0.1 between the reference photo and the reference-view
  render; ``lpips/lpips.safetensors`` (layout and converter: ``morpheus_core/metrics/lpips.py``).
- ``clip_similarity`` (higher = closer): cosine similarity of CLIP image embeddings, each novel
  view vs the photo, mean over views; ``clip/`` with ``config.json``, ``model.safetensors`` or
  ``pytorch_model.bin``, ``preprocessor_config.json`` (a transformers ``CLIPModel`` snapshot).
- ``clipiqa`` (higher = better, in [0, 1]): CLIP-IQA, P("Good photo." over "Bad photo.") per
  view, mean over views; ``clip/`` as above plus the tokenizer, ``tokenizer.json`` or
  ``vocab.json`` (with ``merges.txt``).
- ``maniqa`` (higher = better): MANIQA no-reference quality per view, mean over views;
  ``maniqa/maniqa.onnx`` (contract and export recipe below).

The models root is ``WeightedMetricsConfig.models_root``, else ``$MORPHEUS_MODELS``, else
``~/.cache/morpheus3d/models`` (as for the priors, ``priors/registry.py``); ``folders`` replaces a
metric's sub-folder (absolute, or relative to the root). ``clip_similarity`` and ``clipiqa`` share
``clip/`` by default and then share one loaded model. Nothing is ever downloaded: transformers
loads with ``local_files_only=True`` and ``HF_HUB_OFFLINE=1``.

Outcomes per metric (``MetricResult``), so one absent or broken model never stops the QA of a
catalog:

- ``ok``: a finite value (and the per-view values where there are views);
- ``skipped``: disabled in the config, or weights missing — the detail then starts with
  ``"skipped: weights missing (expected files "`` and lists every expected file, the folder,
  which files are absent and how to provide them;
- ``error``: the folder is complete but a file cannot be loaded (truncated safetensors, wrong
  key layout, an ONNX model with another input/output contract) or the model failed on the
  images; the detail names the file and the reason. Load failures are remembered for the life of
  a ``WeightedMetrics`` so a corrupt 600 MB file is not re-read for every object.

Invalid *inputs* (wrong shapes, NaN) are the caller's bug and raise ``ValueError``.

Inputs: ``reference`` is the photo's RGB (3×H×W, [0, 1]); ``reference_mask`` its alpha
(H×W or 1×H×W) or None. With a mask the photo is composited over white, the background of the
renders (pass None for a reference already composited, e.g. ``ReferenceTarget.rgb``). ``views``
are N renders (N×3×H'×W') on white. LPIPS compares the reference with ``reference_render``, the
render from the reference camera (defaults to ``views[0]``), resized to the photo's size if needed.

CLIP-IQA follows Wang et al. 2023 / torchmetrics: both image and prompt embeddings are
L2-normalised, logits = ``logit_scale.exp()`` (100 for the released CLIP models) × cosine, softmax
over each antonym pair, probability of the positive prompt. The paper's numbers use a ResNet-50
CLIP; transformers' ``CLIPModel`` is a ViT CLIP, so values are comparable between our runs, not
with the paper's tables.

MANIQA contract (``maniqa.onnx``): input ``N×3×224×224`` float32, RGB in [0, 1] normalised with the
ImageNet mean (0.485, 0.456, 0.406) and std (0.229, 0.224, 0.225); output ``N×1`` float32 score
(higher = better). A model exported with a fixed batch size (MANIQA's per-sample score loop is
unrolled by tracing, so an export at batch 1 is fixed at 1) is fed in chunks of that size. Views
are resized to the model's input size (the original evaluation averages 20 random 224 crops of
larger images; renders are square and close to 224 px, so the whole view is scored).

Exporting MANIQA (on a machine with the MANIQA repository, its requirements and a checkpoint;
not run here — no weights are available offline)::

    # github.com/IIGROUP/MANIQA checkout; in models/maniqa.py replace `torch.tensor([]).cuda()` in
    # MANIQA.forward by `torch.tensor([], device=x.device)` (CPU export) and build timm's ViT with
    # pretrained=False (the checkpoint holds those weights; strict=True below proves it).
    import torch
    from models.maniqa import MANIQA

    MEAN = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    STD = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)

    class Export(torch.nn.Module):  # our ImageNet-normalised input → MANIQA's Normalize(0.5, 0.5)
        def __init__(self, net): super().__init__(); self.net = net
        def forward(self, x): return self.net((x * STD + MEAN - 0.5) / 0.5).reshape(-1, 1)

    net = MANIQA(embed_dim=768, num_outputs=1, dim_mlp=768, patch_size=8, img_size=224, window_size=4,
                 depths=[2, 2], num_heads=[4, 4], num_tab=2, scale=0.8)
    net.load_state_dict(torch.load("ckpt_koniq10k.pt", map_location="cpu"), strict=True)
    torch.onnx.export(Export(net).eval(), torch.rand(1, 3, 224, 224), "maniqa.onnx", input_names=["image"],
                      output_names=["score"], opset_version=17, dynamo=False)

(``predict_one_image.py`` of that repository shows the model arguments and the Normalize(0.5, 0.5)
input the wrapper reproduces; a release saved as a whole pickled module loads with
``torch.load(..., weights_only=False)`` — only for a file you trust.)
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from morpheus_core.imaging import batch_to_uint8_hwc
from morpheus_core.metrics.lpips import LPIPS, LPIPS_FILE
from morpheus_core.metrics.weighted_models import MANIQA_FILE, METRIC_SPECS, LoadedClip, ManiqaOnnx
from morpheus_core.priors.registry import ModelSpec, ModelStatus, models_root, spec_named
from morpheus_core.runtime.devices import pick_device

log = logging.getLogger(__name__)

METRIC_NAMES: tuple[str, ...] = ("lpips", "clip_similarity", "clipiqa", "maniqa")
HIGHER_IS_BETTER: Mapping[str, bool] = {"lpips": False, "clip_similarity": True, "clipiqa": True, "maniqa": True}
# CLIP-IQA's default ("quality") antonym pair; more pairs are averaged.
CLIPIQA_PROMPTS: tuple[tuple[str, str], ...] = (("Good photo.", "Bad photo."),)
SKIP_MISSING = "skipped: weights missing (expected files "

MetricStatus = Literal["ok", "skipped", "error"]


def _spec(name: str) -> ModelSpec:
    return spec_named(METRIC_SPECS, name, "weighted metric")


@dataclass(frozen=True)
class WeightedMetricStatus(ModelStatus):
    """A metric's folder (``ModelStatus``: spec, path, missing files) and whether it is enabled."""

    enabled: bool = True


@dataclass(frozen=True)
class MetricResult:
    """One metric's outcome: ``value`` is None unless ``status == "ok"``; ``detail`` says why/how."""

    name: str
    value: float | None
    status: MetricStatus
    detail: str
    per_view: tuple[float, ...] = ()


@dataclass(frozen=True)
class WeightedMetricsConfig:
    """Where the metric models live and how they run.

    ``models_root`` None means ``$MORPHEUS_MODELS`` or the default root; ``folders`` maps a metric
    name to a folder (absolute, or relative to the root) replacing its default sub-folder.
    ``device`` is ``cpu``, ``cuda[:i]`` or ``auto`` (torch models; MANIQA always runs on
    onnxruntime's CPU provider). ``batch_size`` bounds the views per forward pass.
    """

    models_root: Path | None = None
    folders: Mapping[str, Path] = field(default_factory=dict)
    enabled: frozenset[str] = frozenset(METRIC_NAMES)
    device: str = "cpu"
    batch_size: int = 8
    clipiqa_prompts: tuple[tuple[str, str], ...] = CLIPIQA_PROMPTS

    def __post_init__(self) -> None:
        # Typos fail at configuration time, not after an hour of catalog QA.
        for name in (*self.folders, *self.enabled):
            _spec(name)
        object.__setattr__(self, "enabled", frozenset(self.enabled))
        if self.batch_size < 1:
            raise ValueError(f"batch_size must be ≥ 1, got {self.batch_size}")
        if not self.clipiqa_prompts or any(len(pair) != 2 for pair in self.clipiqa_prompts):
            raise ValueError(f"clipiqa_prompts must be (positive, negative) pairs, got {self.clipiqa_prompts!r}")

    def resolved_root(self) -> tuple[Path, str]:
        if self.models_root is not None:
            return Path(self.models_root).expanduser(), "config"
        return models_root()

    def folder(self, name: str) -> Path:
        spec = _spec(name)
        return self.resolved_root()[0] / Path(self.folders.get(name, spec.folder)).expanduser()

    def status(self, name: str) -> WeightedMetricStatus:
        spec = _spec(name)
        path = self.folder(name)
        missing = tuple(" or ".join(alts) for alts in spec.required if not any((path / a).is_file() for a in alts))
        return WeightedMetricStatus(spec, path, missing, name in self.enabled)


def weighted_metric_status(cfg: WeightedMetricsConfig | None = None) -> list[WeightedMetricStatus]:
    """Every metric's folder, missing files and enabled flag (for a ``doctor`` listing); loads nothing."""
    cfg = cfg or WeightedMetricsConfig()
    return [cfg.status(name) for name in METRIC_NAMES]


def missing_detail(status: ModelStatus) -> str:
    """The skip reason: every expected file, the folder, what is absent and how to provide it."""
    expected = ", ".join(" or ".join(alts) for alts in status.spec.required)
    how_to = status.spec.how_to.replace("<folder>", str(status.path))
    return (f"{SKIP_MISSING}{expected} in {status.path}; missing: {', '.join(status.missing)}). "
            f"Weights are never downloaded; to provide them: {how_to}")


# -- inputs -------------------------------------------------------------------------------------------


def _check_finite(name: str, t: Tensor) -> None:
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name} holds NaN/Inf")


def prepare_inputs(reference: Tensor, reference_mask: Tensor | None, views: Tensor,
                   reference_render: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Validated CPU float copies: reference 1×3×H×W (over white when masked), views N×3×H'×W',
    and the reference-view render 1×3×H×W (resized to the photo's size), all clamped to [0, 1]."""
    if reference.dim() != 3 or reference.shape[0] != 3:
        raise ValueError(f"reference must be 3×H×W RGB, got {tuple(reference.shape)}")
    if views.dim() != 4 or views.shape[1] != 3 or views.shape[0] < 1:
        raise ValueError(f"views must be N×3×H×W with N ≥ 1, got {tuple(views.shape)}")
    ref = reference.detach().float().cpu()
    h, w = ref.shape[-2:]
    if reference_mask is not None:
        m = reference_mask.detach().float().cpu()
        m = m[None] if m.dim() == 2 else m
        if tuple(m.shape) != (1, h, w):
            raise ValueError(f"reference_mask must be H×W or 1×H×W matching {h}×{w}, got {tuple(reference_mask.shape)}")
        _check_finite("reference_mask", m)
        m = m.clamp(0.0, 1.0)
        ref = ref * m + (1.0 - m)  # the renders are on white
    render = views[0] if reference_render is None else reference_render
    render = render.detach().float().cpu()
    render = render[None] if render.dim() == 3 else render
    if render.dim() != 4 or render.shape[:2] != (1, 3):
        raise ValueError(f"reference_render must be 3×H×W or 1×3×H×W, got {tuple(render.shape)}")
    if render.shape[-2:] != (h, w):
        shrink = render.shape[-2] > h or render.shape[-1] > w
        render = F.interpolate(render, size=(h, w), mode="bilinear", align_corners=False, antialias=shrink)
    v = views.detach().float().cpu()
    for name, t in (("reference", ref), ("views", v), ("reference_render", render)):
        _check_finite(name, t)
    return ref[None].clamp(0.0, 1.0), v.clamp(0.0, 1.0), render.clamp(0.0, 1.0)


# -- the metrics -------------------------------------------------------------------------------------


class WeightedMetrics:
    """Loads each configured metric model once (lazily) and scores any number of objects.

    ``compute_weighted_metrics`` builds one per call; keep an instance for a catalog so the
    models are not reloaded per object.
    """

    def __init__(self, cfg: WeightedMetricsConfig | None = None) -> None:
        self.cfg = cfg or WeightedMetricsConfig()
        self.device = pick_device(self.cfg.device)
        self._lpips: dict[Path, LPIPS] = {}
        self._clip: dict[Path, LoadedClip] = {}
        self._maniqa: dict[Path, ManiqaOnnx] = {}
        self._load_errors: dict[tuple[str, Path], str] = {}

    def status(self) -> list[WeightedMetricStatus]:
        return weighted_metric_status(self.cfg)

    def compute(self, reference: Tensor, reference_mask: Tensor | None, views: Tensor,
                reference_render: Tensor | None = None) -> dict[str, MetricResult]:
        """Every metric's ``MetricResult`` (in ``METRIC_NAMES`` order); see the module docstring."""
        ref, v, render = prepare_inputs(reference, reference_mask, views, reference_render)
        return {name: self._one(name, ref, v, render) for name in METRIC_NAMES}

    def _one(self, name: str, ref: Tensor, views: Tensor, render: Tensor) -> MetricResult:
        if name not in self.cfg.enabled:
            return MetricResult(name, None, "skipped", "skipped: disabled (not in WeightedMetricsConfig.enabled)")
        status = self.cfg.status(name)
        if status.missing:
            return MetricResult(name, None, "skipped", missing_detail(status))
        key = (name, status.path)
        if key in self._load_errors:
            return MetricResult(name, None, "error", self._load_errors[key])
        try:
            model = self._load(name, status.path)
        except Exception as exc:  # any loader failure is this metric's error, not the QA run's
            detail = f"error: cannot load {name} from {status.path}: {type(exc).__name__}: {exc}"
            log.warning(detail)
            self._load_errors[key] = detail
            return MetricResult(name, None, "error", detail)
        try:
            with torch.inference_mode():
                value, per_view, detail = self._run(name, model, ref, views, render)
        except Exception as exc:
            detail = f"error: {name} (model in {status.path}) failed: {type(exc).__name__}: {exc}"
            log.warning(detail)
            return MetricResult(name, None, "error", detail)
        if not np.isfinite(value):
            return MetricResult(name, None, "error", f"error: {name} (model in {status.path}) gave {value}")
        return MetricResult(name, value, "ok", detail, per_view)

    # -- loading ----------------------------------------------------------------------------------

    def _load(self, name: str, folder: Path) -> Any:
        if name == "lpips":
            if folder not in self._lpips:
                self._lpips[folder] = LPIPS.from_file(folder / LPIPS_FILE).to(self.device)
            return self._lpips[folder]
        if name in ("clip_similarity", "clipiqa"):
            clip = self._load_clip(folder)
            if name == "clipiqa" and clip.tokenizer is None:
                from transformers import CLIPTokenizer

                clip.tokenizer = CLIPTokenizer.from_pretrained(str(folder), local_files_only=True)
            return clip
        if folder not in self._maniqa:
            self._maniqa[folder] = ManiqaOnnx(folder / MANIQA_FILE)
        return self._maniqa[folder]

    def _load_clip(self, folder: Path) -> LoadedClip:
        """One CLIPModel per folder, shared by CLIP similarity and CLIP-IQA."""
        if folder not in self._clip:
            from transformers import CLIPImageProcessor, CLIPModel

            model = CLIPModel.from_pretrained(str(folder), local_files_only=True).to(self.device).eval()
            processor = CLIPImageProcessor.from_pretrained(str(folder), local_files_only=True)
            self._clip[folder] = LoadedClip(model, processor)
        return self._clip[folder]

    # -- running ----------------------------------------------------------------------------------

    def _run(self, name: str, model: Any, ref: Tensor, views: Tensor,
             render: Tensor) -> tuple[float, tuple[float, ...], str]:
        if name == "lpips":
            d = float(model(ref.to(self.device), render.to(self.device))[0])
            h, w = ref.shape[-2:]
            return d, (), f"LPIPS ({model.trunk.name}) photo vs reference-view render at {h}×{w}; lower = closer"
        if name == "clip_similarity":
            e_ref = self._image_embeddings(model, ref)
            e_views = self._image_embeddings(model, views)
            sims = (e_views @ e_ref[0]).cpu()
            return float(sims.mean()), _floats(sims), f"mean CLIP cosine similarity of {len(views)} views to the photo"
        if name == "clipiqa":
            probs = self._clipiqa(model, views)
            return float(probs.mean()), _floats(probs), (
                f"CLIP-IQA P(positive prompt) over {len(self.cfg.clipiqa_prompts)} prompt pair(s), mean of "
                f"{len(views)} views")
        scores = model.scores(views, self.cfg.batch_size)
        return float(scores.mean()), _floats(scores), f"MANIQA mean of {len(views)} views at {model.size}"

    def _image_embeddings(self, clip: LoadedClip, images: Tensor) -> Tensor:
        """L2-normalised projected CLIP image embeddings (N×D), in batches of ``batch_size``."""
        out: list[Tensor] = []
        dtype = next(clip.model.parameters()).dtype
        for start in range(0, len(images), self.cfg.batch_size):
            frames = batch_to_uint8_hwc(images[start:start + self.cfg.batch_size])
            pixels = clip.processor(images=frames, return_tensors="pt").pixel_values.to(self.device, dtype)
            # vision tower + projection directly: get_image_features returns a tensor in transformers 4
            # and a model output in 5; these two calls are the same computation in both.
            pooled = clip.model.vision_model(pixel_values=pixels).pooler_output
            out.append(F.normalize(clip.model.visual_projection(pooled).float(), dim=-1))
        return torch.cat(out)

    def _clipiqa(self, clip: LoadedClip, views: Tensor) -> Tensor:
        prompts = [p for pair in self.cfg.clipiqa_prompts for p in pair]
        tokens = clip.tokenizer(prompts, padding=True, return_tensors="pt")
        text = clip.model.text_model(input_ids=tokens["input_ids"].to(self.device),
                                     attention_mask=tokens["attention_mask"].to(self.device)).pooler_output
        anchors = F.normalize(clip.model.text_projection(text).float(), dim=-1)  # 2P×D
        images = self._image_embeddings(clip, views)  # N×D
        logits = clip.model.logit_scale.exp().float() * images @ anchors.T  # N×2P
        probs = logits.view(len(views), -1, 2).softmax(dim=-1)[..., 0]  # N×P: P(positive) per pair
        return probs.mean(dim=1).cpu()


def _floats(t: Tensor) -> tuple[float, ...]:
    return tuple(float(x) for x in t.reshape(-1))


def compute_weighted_metrics(reference: Tensor, reference_mask: Tensor | None, views: Tensor,
                             cfg: WeightedMetricsConfig | None = None, *,
                             reference_render: Tensor | None = None) -> dict[str, MetricResult]:
    """Every metric for one object: ``{name: MetricResult}`` in ``METRIC_NAMES`` order.

    ``reference`` 3×H×W and ``views`` N×3×H'×W' in [0, 1]; ``reference_mask`` H×W / 1×H×W alpha of
    the photo or None; ``reference_render`` the reference-camera render (default ``views[0]``).
    Missing weights give ``skipped`` records, unreadable ones ``error`` records — never a download.
    For many objects, keep one ``WeightedMetrics(cfg)`` and call its ``compute``.
    """
    return WeightedMetrics(cfg).compute(reference, reference_mask, views, reference_render)

