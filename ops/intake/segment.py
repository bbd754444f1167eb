"""The segmentation chain: the photo's own alpha, else rembg (local model only), else classical.

Every step records what it did and why it was skipped or rejected, so a user sees exactly which
method produced each mask. Segmentation runs at ``work_size`` (longest side) for speed; the soft
alpha is then resized back to the loaded photo.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from morpheus_core.imaging import fit_within, resize, touched_borders
from morpheus_core.segmentation.mask_confidence import ConfidenceParams, MaskConfidence, mask_confidence
from morpheus_core.segmentation.mask_ops import ClassicalParams, classical_segment, fill_holes
from morpheus_core.segmentation.mask_parts import PartRecord, kept_count, scaled_parts, select_parts
from ops.intake.errors import LowConfidenceError, SegmentationError
from ops.intake.photo import Photo
from ops.intake.rembg_local import U2NetSession, find_model, model_candidates


@dataclass(frozen=True)
class SegmentConfig:
    classical: ClassicalParams = field(default_factory=ClassicalParams)
    use_rembg: bool = True
    """Try rembg's u2net (local model only) before the classical chain when the photo has no alpha."""
    rembg_model: Path | None = None
    """A u2net .onnx file or a folder holding one; None: ``$U2NET_HOME`` (default ``~/.u2net``)."""
    work_size: int = 512
    """Longest side (px) segmentation runs at, for speed; the soft alpha is resized back to the photo."""
    min_area_fraction: float = 0.005
    """Smallest share of the image the mask may cover; smaller is an error (a product cannot be that small)."""
    max_area_fraction: float = 0.9
    """Mask share of the image above which to warn (the background was probably not separated)."""
    border_touch_fraction: float = 0.01
    """Share of an image edge's pixels the object may cover before a "touches the border" warning."""
    max_background_spread: float = 8.0
    """Border ΔE spread above which to warn: classical segmentation assumes a near-uniform background."""
    confidence: ConfidenceParams = field(default_factory=ConfidenceParams)
    ok_confidence: float = 0.5
    """Mask confidence (0–1) below which a warning is recorded."""
    min_confidence: float = 0.15
    """Mask confidence (0–1) below which the photo stops here (LowConfidenceError), not at the GPU stages."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_confidence <= self.ok_confidence <= 1.0:
            raise ValueError(f"need 0 ≤ min_confidence ≤ ok_confidence ≤ 1, got {self.min_confidence}, "
                             f"{self.ok_confidence}")


@dataclass(frozen=True)
class ChainStep:
    step: str  # "alpha" | "rembg" | "classical"
    outcome: str  # "used" | "skipped" | "rejected"
    detail: str


@dataclass(frozen=True)
class MaskResult:
    alpha: np.ndarray = field(repr=False)  # H×W float32 at the loaded photo's size
    method: str
    chain: tuple[ChainStep, ...]
    warnings: tuple[str, ...]
    model_path: Path | None
    confidence: MaskConfidence
    parts: tuple[PartRecord, ...]  # bboxes in the loaded photo's pixels


def mask_problems(mask: np.ndarray, cfg: SegmentConfig) -> tuple[str | None, list[str]]:
    """(fatal reason or None, warnings) for a binary mask."""
    area = float(mask.mean())
    if area == 0.0:
        return "the mask is empty (no object found)", []
    if area < cfg.min_area_fraction:
        return f"the object covers only {area:.2%} of the image (minimum {cfg.min_area_fraction:.1%})", []
    warnings = []
    sides = touched_borders(mask, cfg.border_touch_fraction)
    if sides:
        warnings.append(f"object touches the image border ({', '.join(sides)}): it may be cut off")
    if area > cfg.max_area_fraction:
        warnings.append(f"mask covers {area:.0%} of the image: segmentation likely failed")
    return None, warnings


ALPHA_CONFIDENCE = MaskConfidence(1.0, {"alpha": 1.0}, {"alpha": 1.0})  # the photo's own alpha is the truth
LOW_CONFIDENCE_FIX = ("this does not look like a product on a plain backdrop: supply a PNG with an alpha channel, "
                      "install a u2net model under $U2NET_HOME (or pass --rembg-model), or photograph the product on "
                      "a plainer backdrop; to accept such masks lower segment.min_confidence")


def _tidy(alpha: np.ndarray) -> tuple[np.ndarray, tuple[PartRecord, ...]]:
    """Keep the product's parts and their holes; zero stray haze elsewhere (a soft edge is kept)."""
    parts_mask, parts = select_parts(alpha >= 0.5)
    keep = cv2.dilate(fill_holes(parts_mask).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    return np.where(keep, alpha, 0.0).astype(np.float32), parts



class Segmenter:
    """Runs the chain; holds the rembg session so it is created once per process, not per photo."""

    def __init__(self, cfg: SegmentConfig | None = None) -> None:
        self.cfg = cfg or SegmentConfig()
        self._session: U2NetSession | None = None

    def _rembg(self) -> tuple[U2NetSession | None, str]:
        if not self.cfg.use_rembg:
            return None, "disabled by configuration"
        model = find_model(self.cfg.rembg_model)
        if model is None:
            tried = " or ".join(str(p) for p in model_candidates(self.cfg.rembg_model))
            return None, f"no u2net model at {tried} (set $U2NET_HOME or --rembg-model; nothing is downloaded)"
        if self._session is None or self._session.model_path != model:
            self._session = U2NetSession(model)
        return self._session, f"model {model}"

    def segment(self, photo: Photo) -> MaskResult:
        chain: list[ChainStep] = []
        if photo.alpha is not None:
            fatal, warnings = mask_problems(photo.alpha >= 0.5, self.cfg)
            if fatal:
                raise SegmentationError(photo.path, f"alpha channel: {fatal}", "export the photo with the product "
                                        "visible, or without an alpha channel so it gets segmented")
            chain.append(ChainStep("alpha", "used", "photo has a meaningful alpha channel: segmentation left out"))
            parts = select_parts(photo.alpha >= 0.5)[1]
            return MaskResult(photo.alpha, "alpha", tuple(chain), tuple(warnings), None, ALPHA_CONFIDENCE, parts)
        chain.append(ChainStep("alpha", "skipped", "photo has no (non-trivial) alpha channel"))
        h, w = photo.rgb.shape[:2]
        small = resize(photo.rgb, fit_within((w, h), self.cfg.work_size))
        session, detail = self._rembg()
        if session is not None:
            alpha, parts = _tidy(session.predict(small))
            fatal, warnings = mask_problems(alpha >= 0.5, self.cfg)
            if fatal is None:
                confidence = mask_confidence(alpha >= 0.5, kept_count(parts), self.cfg.confidence)
                self._judge(photo, confidence, warnings, "rembg mask")
                chain.append(ChainStep("rembg", "used", f"{detail}, confidence {confidence.score:.2f}"))
                return MaskResult(self._full(alpha, (w, h)), "rembg", tuple(chain), tuple(warnings), session.model_path,
                                  confidence, scaled_parts(parts, w / alpha.shape[1], h / alpha.shape[0]))
            chain.append(ChainStep("rembg", "rejected", f"{detail}: {fatal}"))
        else:
            chain.append(ChainStep("rembg", "skipped", detail))
        return self._classical(photo, small, chain)

    def _classical(self, photo: Photo, small: np.ndarray, chain: list[ChainStep]) -> MaskResult:
        result = classical_segment(small, self.cfg.classical)
        fatal, warnings = mask_problems(result.mask, self.cfg)
        if fatal:
            raise SegmentationError(
                photo.path, f"classical segmentation: {fatal}",
                "photograph the product on a plain background, supply a PNG with alpha, or install a u2net "
                "model under $U2NET_HOME",
            )
        if result.background_spread > self.cfg.max_background_spread:
            warnings.insert(0, f"background is not near-uniform (border ΔE spread {result.background_spread:.1f} > "
                            f"{self.cfg.max_background_spread:g}): the classical mask may be wrong")
        kept = kept_count(result.parts)
        confidence = mask_confidence(result.mask, kept, self.cfg.confidence, backdrop_spread=result.background_spread,
                                     edges=result.edges.edges, cue_pixels=result.cue_pixels)
        self._judge(photo, confidence, warnings, "classical mask")
        outlined = int((result.edges.regions & ~result.colour_seed).sum())
        grabcut = "refined by GrabCut" if result.grabcut_used else "GrabCut result discarded (diverged from the seed)"
        detail = (f"border ΔE spread {result.background_spread:.1f}, {kept} part(s), "
                  f"confidence {confidence.score:.2f}, {grabcut}"
                  + (f", {outlined} px found by the edge cue only" if outlined else ""))
        chain.append(ChainStep("classical", "used", detail))
        h, w = photo.rgb.shape[:2]
        sx, sy = w / small.shape[1], h / small.shape[0]
        return MaskResult(self._full(result.mask.astype(np.float32), (w, h)), "classical", tuple(chain),
                          tuple(warnings), None, confidence, scaled_parts(result.parts, sx, sy))

    def _judge(self, photo: Photo, confidence: MaskConfidence, warnings: list[str], what: str) -> None:
        """Stop a photo whose mask confidence is below ``min_confidence``; warn below ``ok_confidence``."""
        weakest = ", ".join(confidence.weakest())
        if confidence.score < self.cfg.min_confidence:
            raise LowConfidenceError(photo.path, f"{what} confidence {confidence.score:.2f} is below "
                                     f"{self.cfg.min_confidence:g} (weakest: {weakest})", LOW_CONFIDENCE_FIX)
        if confidence.score < self.cfg.ok_confidence:
            warnings.append(f"{what} confidence {confidence.score:.2f} is below {self.cfg.ok_confidence:g} "
                            f"(weakest: {weakest}): check the mask preview")

    @staticmethod
    def _full(alpha: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        if alpha.shape[::-1] == size:
            return alpha
        return np.clip(cv2.resize(alpha, size, interpolation=cv2.INTER_LINEAR), 0.0, 1.0)
