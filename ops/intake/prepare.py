"""Prepare a photo into a reference folder: RGBA + mask at each size and ``reference.json``.

A folder is written whole or not at all: everything goes into a hidden sibling temporary folder
that is renamed into place at the end, so a crash leaves the old folder or none. ``reference.json``
is the completion marker; ``read_reference`` treats a folder without a valid one as not prepared.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from morpheus_core.imaging import bbox, recentre
from morpheus_core.segmentation.mask_parts import PartRecord, kept_count, scale_box, scaled_parts
from ops.intake.errors import PreparationError
from ops.intake.photo import LoadConfig, load_photo
from ops.intake.segment import ChainStep, SegmentConfig, Segmenter

SCHEMA = 2  # 2: the mask's parts (kept and dropped, with why) and its confidence
REFERENCE_FILE = "reference.json"


@dataclass(frozen=True)
class PrepareConfig:
    load: LoadConfig = field(default_factory=LoadConfig)
    segment: SegmentConfig = field(default_factory=SegmentConfig)
    sizes: tuple[int, ...] = (256, 512)
    """Sides (px) of the square recentred references written (``rgba_<size>.png``); others are resized from these."""
    border_ratio: float = 0.1
    """Empty margin on each side of the object's longer side: it fills 1 − 2·border_ratio of the square."""

    def to_dict(self) -> dict[str, Any]:
        return json.loads(json.dumps(asdict(self), default=str))


@dataclass(frozen=True)
class ReferenceInfo:
    """What ``reference.json`` holds; coordinates are in source pixels after EXIF orientation."""

    source_path: str
    source_sha256: str
    source_format: str
    source_mode: str
    source_size: tuple[int, int]
    loaded_size: tuple[int, int]
    notes: tuple[str, ...]
    method: str
    model_path: str | None
    chain: tuple[ChainStep, ...]
    bbox: tuple[int, int, int, int]
    area_fraction: float
    warnings: tuple[str, ...]
    border_ratio: float
    files: dict[str, str]
    config: dict[str, Any]
    # Every connected part of the mask, largest first; bboxes in source pixels like ``bbox``.
    parts: tuple[PartRecord, ...] = ()
    confidence: dict[str, Any] = field(default_factory=dict)  # score, factors, measurements
    schema: int = SCHEMA

    @property
    def status(self) -> str:
        return "warning" if self.warnings else "ok"

    @property
    def kept_parts(self) -> int:
        return kept_count(self.parts)

    @property
    def object_long_side_px(self) -> int:
        x0, y0, x1, y1 = self.bbox
        return max(x1 - x0, y1 - y0)

    def to_json(self) -> str:
        data = asdict(self)
        data["status"] = self.status
        return json.dumps(data, indent=2, sort_keys=True, allow_nan=False, ensure_ascii=False)

    @classmethod
    def from_json(cls, text: str) -> ReferenceInfo:
        data = json.loads(text)
        data.pop("status", None)
        if data.get("schema") != SCHEMA:
            raise ValueError(f"reference schema {data.get('schema')!r}, expected {SCHEMA}")
        data["chain"] = tuple(ChainStep(**c) for c in data["chain"])
        data["parts"] = tuple(PartRecord(**{**p, "bbox": tuple(p["bbox"])}) for p in data["parts"])
        for key in ("source_size", "loaded_size", "bbox", "notes", "warnings"):
            data[key] = tuple(data[key])
        return cls(**data)


def read_reference(folder: Path) -> ReferenceInfo | None:
    """The folder's reference, or None when it is missing, invalid or lacks one of its files."""
    try:
        info = ReferenceInfo.from_json((Path(folder) / REFERENCE_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError, TypeError, KeyError):
        return None
    return info if all((Path(folder) / f).is_file() for f in info.files.values()) else None


def _is_replaceable(folder: Path) -> bool:
    """Only an empty folder or one we wrote (it has reference.json) may be replaced wholesale."""
    return not folder.exists() or (folder.is_dir() and (not any(folder.iterdir()) or
                                                         (folder / REFERENCE_FILE).is_file()))


def _commit(tmp: Path, final: Path) -> None:
    old = final.with_name(f".{final.name}.old.{os.getpid()}")
    if final.exists():
        os.replace(final, old)
    os.replace(tmp, final)
    shutil.rmtree(old, ignore_errors=True)


def _fsync(path: Path) -> None:
    # The folder rename is atomic, but its files must be on disk before it, or a power cut
    # could leave a renamed folder of empty files.
    with open(path, "rb") as fh:
        os.fsync(fh.fileno())


def _save_png(array: np.ndarray, path: Path) -> None:
    Image.fromarray(array).save(path, format="PNG")
    _fsync(path)


def prepare_reference(photo_path: Path | str, out_dir: Path | str, cfg: PrepareConfig | None = None,
                      segmenter: Segmenter | None = None) -> ReferenceInfo:
    """Load, segment, recentre and write one photo's reference folder (see the module docstring).

    Raises ``PreparationError`` subclasses (naming the file and the fix); writes nothing then.
    """
    cfg = cfg or PrepareConfig()
    out_dir = Path(out_dir)
    if not _is_replaceable(out_dir):
        raise PreparationError(out_dir, "the output folder exists and is not a reference folder",
                               "choose an empty or new --out folder")
    segmenter = segmenter or Segmenter(cfg.segment)
    photo = load_photo(photo_path, cfg.load)
    result = segmenter.segment(photo)
    binary = result.alpha >= 0.5
    box = bbox(binary)
    assert box is not None  # the chain raises on empty masks
    lw, lh = photo.size
    sx, sy = photo.source_size[0] / lw, photo.source_size[1] / lh
    files: dict[str, str] = {}
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_dir.with_name(f".{out_dir.name}.tmp.{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        for size in cfg.sizes:
            ref = recentre(photo.rgb, result.alpha, box, size, cfg.border_ratio)
            rgba = ref.rgba_u8()
            files[f"rgba_{size}"], files[f"mask_{size}"] = f"rgba_{size}.png", f"mask_{size}.png"
            _save_png(rgba, tmp / files[f"rgba_{size}"])
            _save_png(rgba[..., 3], tmp / files[f"mask_{size}"])
        info = ReferenceInfo(
            source_path=str(photo.path.resolve()), source_sha256=photo.sha256, source_format=photo.format,
            source_mode=photo.mode, source_size=photo.source_size, loaded_size=photo.size, notes=photo.notes,
            method=result.method, model_path=None if result.model_path is None else str(result.model_path),
            chain=result.chain,
            bbox=scale_box(box, sx, sy),
            area_fraction=float(binary.mean()), warnings=result.warnings, border_ratio=cfg.border_ratio,
            files=files, config=cfg.to_dict(),
            parts=scaled_parts(result.parts, sx, sy),
            confidence=asdict(result.confidence),
        )
        (tmp / REFERENCE_FILE).write_text(info.to_json(), encoding="utf-8")
        _fsync(tmp / REFERENCE_FILE)
        _commit(tmp, out_dir)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return info
