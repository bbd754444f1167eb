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
from morpheus_core.mask_ops import ClassicalParams, classical_segment, fill_holes, largest_component
from ops.errors import SegmentationError
from ops.photo import Photo
from ops.rembg_local import U2NetSession, find_model, model_candidates


@dataclass(frozen=True)
class SegmentConfig:
    classical: ClassicalParams = field(default_factory=ClassicalParams)
    use_rembg: bool = True
    rembg_model: Path | None = None  # a u2net .onnx file or a folder holding one; None: $U2NET_HOME
    work_size: int = 512
    min_area_fraction: float = 0.005  # smaller objects: error (the product cannot be that small)
    max_area_fraction: float = 0.9  # larger: warning (the background was probably not separated)
    border_touch_fraction: float = 0.01  # share of an image edge covered by the object before warning
    # Classical segmentation assumes a near-uniform background: warn above this border ΔE spread.
    max_background_spread: float = 8.0


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


def _tidy(alpha: np.ndarray) -> np.ndarray:
    """Keep the main object and its holes; zero stray haze elsewhere (a soft edge is kept)."""
    keep = fill_holes(largest_component(alpha >= 0.5))
    keep = cv2.dilate(keep.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    return np.where(keep, alpha, 0.0).astype(np.float32)


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
            return MaskResult(photo.alpha, "alpha", tuple(chain), tuple(warnings), None)
        chain.append(ChainStep("alpha", "skipped", "photo has no (non-trivial) alpha channel"))
        h, w = photo.rgb.shape[:2]
        small = resize(photo.rgb, fit_within((w, h), self.cfg.work_size))
        session, detail = self._rembg()
        if session is not None:
            alpha = _tidy(session.predict(small))
            fatal, warnings = mask_problems(alpha >= 0.5, self.cfg)
            if fatal is None:
                chain.append(ChainStep("rembg", "used", detail))
                return MaskResult(self._full(alpha, (w, h)), "rembg", tuple(chain), tuple(warnings), session.model_path)
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
        detail = f"border ΔE spread {result.background_spread:.1f}, " + (
            "refined by GrabCut" if result.grabcut_used else "GrabCut result discarded (diverged from the seed)")
        chain.append(ChainStep("classical", "used", detail))
        h, w = photo.rgb.shape[:2]
        return MaskResult(self._full(result.mask.astype(np.float32), (w, h)), "classical", tuple(chain),
                          tuple(warnings), None)

    @staticmethod
    def _full(alpha: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        if alpha.shape[::-1] == size:
            return alpha
        return np.clip(cv2.resize(alpha, size, interpolation=cv2.INTER_LINEAR), 0.0, 1.0)
