"""Typed failures of reference preparation. Every message names the file, the reason and the fix.

A batch runner catches ``PreparationError`` per photo and keeps going; anything else is a bug.
"""

from __future__ import annotations

from pathlib import Path


class PreparationError(Exception):
    """A photo that cannot be turned into a reference; ``reason`` and ``fix`` are for people."""

    def __init__(self, path: Path | str, reason: str, fix: str) -> None:
        self.path = Path(path)
        self.reason = reason
        self.fix = fix
        super().__init__(f"{self.path}: {reason}. Fix: {fix}")


class InvalidImageError(PreparationError):
    """Not a readable image: truncated, not an image at all, unsupported format, unusable size."""


class ImageTooLargeError(InvalidImageError):
    """More pixels than the configured limit (also Pillow's decompression-bomb guard)."""


class SegmentationError(PreparationError):
    """No usable object mask: empty, or too small to be the product."""


class LowConfidenceError(SegmentationError):
    """A mask was found but does not look like one product on a plain backdrop (confidence too low)."""
