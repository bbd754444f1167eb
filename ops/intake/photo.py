"""Loading a user's photo into float RGB (+ alpha) safely, whatever the file looks like.

Accepted: JPEG (and camera MPO), PNG, WebP, TIFF, BMP. EXIF orientation is applied; palette,
grayscale, CMYK, 16-bit and float images become sRGB floats in [0, 1]. Pillow's global
decompression-bomb guard is turned into our typed error (never a warning that scrolls past),
and a configurable pixel limit applies before any pixel is decoded.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

from assets_store.hashing import file_sha256
from ops.intake.errors import ImageTooLargeError, InvalidImageError

FORMATS = frozenset({"JPEG", "MPO", "PNG", "WEBP", "TIFF", "BMP"})
EXTENSIONS = frozenset({".jpg", ".jpeg", ".jpe", ".png", ".webp", ".tif", ".tiff", ".bmp"})
_ALPHA_MODES = frozenset({"RGBA", "LA", "PA", "RGBa", "La"})


@dataclass(frozen=True)
class LoadConfig:
    """Limits on what a photo may be, and how it is shrunk right after decoding."""

    max_pixels: int = 40_000_000
    """Largest photo accepted (width × height, px); must stay under Pillow's own decompression-bomb limit."""
    min_side: int = 32
    """Smallest shorter side (px) a photo may have."""
    max_aspect: float = 12.0
    """Largest longer/shorter side ratio a photo may have."""
    max_side: int = 3072
    """Longest side (px) after decoding: outputs are ≤ 512 px, and a 40 MP float image costs ~0.5 GB a worker."""
    min_transparent_fraction: float = 0.01
    """An alpha channel counts only when at least this share of pixels is transparent (alpha < 0.5)."""

    def __post_init__(self) -> None:
        pillow_limit = Image.MAX_IMAGE_PIXELS
        if pillow_limit is not None and self.max_pixels > pillow_limit:
            raise ValueError(
                f"max_pixels={self.max_pixels} exceeds Pillow's decompression-bomb limit {pillow_limit}; "
                "Pillow would refuse those images first"
            )
        if self.min_side < 1 or self.max_side < self.min_side or self.max_aspect < 1:
            raise ValueError(f"inconsistent size limits in {self}")


@dataclass(frozen=True)
class Photo:
    """A decoded photo: ``rgb`` H×W×3 float32 in [0, 1]; ``alpha`` H×W float32 or None when absent/trivial."""

    path: Path
    sha256: str
    format: str
    mode: str
    source_size: tuple[int, int]  # (width, height) after EXIF orientation, before any shrink
    rgb: np.ndarray = field(repr=False)
    alpha: np.ndarray | None = field(repr=False)
    exif_transposed: bool
    notes: tuple[str, ...]

    @property
    def size(self) -> tuple[int, int]:
        return self.rgb.shape[1], self.rgb.shape[0]


def _open(path: Path) -> Image.Image:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            return Image.open(path)
    except (Image.DecompressionBombWarning, Image.DecompressionBombError) as exc:
        raise ImageTooLargeError(
            path, f"rejected as a possible decompression bomb ({exc})", "re-export the photo at a sane size"
        ) from exc
    except UnidentifiedImageError as exc:
        raise InvalidImageError(
            path, "not a readable image (content is not JPEG/PNG/WebP/TIFF/BMP)", "re-export or remove this file"
        ) from exc


def _check_geometry(path: Path, img: Image.Image, cfg: LoadConfig) -> None:
    w, h = img.size
    if w * h > cfg.max_pixels:
        raise ImageTooLargeError(
            path, f"{w}×{h} = {w * h:,} pixels exceeds the limit of {cfg.max_pixels:,}",
            "downscale the photo or raise LoadConfig.max_pixels",
        )
    if min(w, h) < cfg.min_side:
        raise InvalidImageError(
            path, f"{w}×{h} px is too small (shorter side under {cfg.min_side} px)", "use a larger photo"
        )
    if max(w, h) / min(w, h) > cfg.max_aspect:
        raise InvalidImageError(
            path, f"{w}×{h} px has aspect ratio {max(w, h) / min(w, h):.0f}:1 (limit {cfg.max_aspect:g}:1); "
            "a product photo is not a strip", "crop the photo around the product",
        )


def _to_arrays(img: Image.Image) -> tuple[np.ndarray, np.ndarray | None]:
    """float32 RGB in [0, 1] and alpha (or None) from any Pillow mode."""
    mode = img.mode
    if mode.startswith("I") or mode == "F":
        # Pillow cannot convert 16-bit/float data to RGB without clipping to 8 bits: scale here.
        arr = np.asarray(img).astype(np.float64)
        if not np.isfinite(arr).all():
            raise ValueError("the image holds NaN or infinite pixel values")
        if mode == "F":
            scale = 1.0 if arr.max(initial=0.0) <= 1.0 else arr.max()
        else:
            scale = 65535.0 if arr.max(initial=0.0) <= 65535 else arr.max()
        grey = np.clip(arr / max(scale, 1e-12), 0.0, 1.0).astype(np.float32)
        return np.repeat(grey[..., None], 3, axis=2), None
    has_alpha = mode in _ALPHA_MODES or (mode == "P" and "transparency" in img.info)
    if mode == "RGBa" or mode == "La":  # premultiplied: un-premultiply through Pillow
        img = img.convert("RGBA")
    converted = np.asarray(img.convert("RGBA" if has_alpha else "RGB"), dtype=np.float32) / 255.0
    if has_alpha:
        return np.ascontiguousarray(converted[..., :3]), np.ascontiguousarray(converted[..., 3])
    return converted, None


def _shrink(rgb: np.ndarray, alpha: np.ndarray | None, max_side: int) -> tuple[np.ndarray, np.ndarray | None]:
    import cv2

    h, w = rgb.shape[:2]
    if max(h, w) <= max_side:
        return rgb, alpha
    s = max_side / max(h, w)
    size = (max(1, round(w * s)), max(1, round(h * s)))
    rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
    return rgb, None if alpha is None else cv2.resize(alpha, size, interpolation=cv2.INTER_AREA)


def load_photo(path: Path | str, cfg: LoadConfig | None = None) -> Photo:
    """Decode ``path`` or raise ``InvalidImageError``/``ImageTooLargeError`` naming the file and the fix."""
    cfg = cfg or LoadConfig()
    path = Path(path)
    if not path.is_file():
        raise InvalidImageError(path, "no such file", "check the path")
    if path.stat().st_size == 0:
        raise InvalidImageError(path, "the file is empty (0 bytes)", "re-copy the photo")
    digest = file_sha256(path)
    img = _open(path)
    with img:
        fmt = img.format or "?"
        if fmt not in FORMATS:
            raise InvalidImageError(path, f"unsupported image format {fmt}", "convert it to PNG or JPEG")
        notes: list[str] = []
        if getattr(img, "n_frames", 1) > 1:
            notes.append(f"{img.n_frames} frames/pages: the first one is used")
        _check_geometry(path, img, cfg)
        orientation = img.getexif().get(0x0112, 1)
        w, h = img.size
        source_size = (h, w) if orientation in (5, 6, 7, 8) else (w, h)  # those orientations swap the axes
        try:
            if fmt == "JPEG":
                img.draft("RGB", (cfg.max_side, cfg.max_side))  # decode JPEGs shrunk by the codec: far faster
            img.load()
            oriented = ImageOps.exif_transpose(img)
            rgb, alpha = _to_arrays(oriented)
        except (OSError, SyntaxError, ValueError, EOFError) as exc:
            raise InvalidImageError(
                path, f"cannot decode the pixel data ({exc})", "the file is probably truncated; re-copy or re-export it"
            ) from exc
        transposed = orientation not in (1, None)
        mode = img.mode
    if transposed:
        notes.append("EXIF orientation applied")
    rgb, alpha = _shrink(rgb, alpha, cfg.max_side)
    if alpha is not None:
        transparent = float((alpha < 0.5).mean())
        if transparent < cfg.min_transparent_fraction:
            notes.append(f"alpha channel ignored: only {transparent:.1%} of pixels are transparent")
            alpha = None
    return Photo(path, digest, fmt, mode, source_size, rgb, alpha, transposed, tuple(notes))
