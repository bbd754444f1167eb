"""Calibrate and measure reference preparation; writes benchmarks/results/prepare_calibration.{json,md}.

1. The segmentation chain (no rembg model: the classical chain, as on a machine without weights) on
   every calibration photo: the generated studio set (every shape × background, seeds 1–5),
   generated white-on-white photos at ΔE 4–12, generated multi-part photos (2–4 parts, 10–60 px
   apart), and the real photographs that installed packages ship (scikit-image's data, Matplotlib's
   sample data) plus the bundled examples. Per photo: outcome (ok / warning / error), mask
   confidence, IoU where a truth exists, parts kept, seconds.
2. The high-frequency ratio of flat vs textured objects (the plan's ``hf_threshold``).
3. Time per photo for ``prepare_reference`` at default settings on the bundled example photos.

    .venv/bin/python -m benchmarks.prepare_calibration   (from the repository root: it reuses tests/photo_factory.py)

``--before FILE`` puts an earlier run's rows (same photos, older code) beside this run's in the table;
``--segmentation-only`` writes only part 1 (to ``--out``/prepare_calibration_segmentation.json).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import matplotlib
import numpy as np
import skimage.data
from PIL import Image

from morpheus_core.imaging import bbox, object_high_frequency_ratio, recentre
from morpheus_core.segmentation.mask_ops import iou
from ops.intake.errors import PreparationError
from ops.intake.photo import load_photo
from ops.intake.plan import MEASURE_SIZE, PlanConfig
from ops.intake.prepare import prepare_reference
from ops.intake.segment import SegmentConfig, Segmenter
from tests.photo_factory import (
    BACKGROUNDS,
    SHAPES,
    TEXTURES,
    PhotoSpec,
    multipart_photo,
    product_photo,
    segmentation_set,
    white_on_white_photo,
)

ROOT = Path(__file__).resolve().parent.parent
DELTA_ES = (4, 6, 8, 12)
PART_COUNTS = (2, 3, 4)
GAPS_PX = (10, 20, 40, 60)
# Real photographs with no product on a plain backdrop: each must end as a warning or an error.
CLUTTERED = ("astronaut.png", "coffee.png", "chelsea.png", "rocket.jpg", "motorcycle_left.png", "camera.png",
             "grace_hopper.jpg", "brick.png", "grass.png", "gravel.png", "hubble_deep_field.jpg", "retina.jpg",
             "ihc.png", "page.png", "text.png", "clock_motion.png", "color.png")


@dataclass(frozen=True)
class CalibrationPhoto:
    group: str  # "studio" | "white" | "multipart" | "real" | "example"
    name: str
    path: Path
    parts: tuple[np.ndarray, ...] | None  # true mask per part, when the truth is known


def _save(folder: Path, name: str, rgb: np.ndarray) -> Path:
    path = folder / f"{name}.png"
    Image.fromarray(rgb).save(path)
    return path


def calibration_photos(folder: Path) -> Iterator[CalibrationPhoto]:
    for seed in range(1, 6):
        for spec in segmentation_set(seed):
            rgb, truth = product_photo(spec)
            name = f"{spec.shape}-{spec.background}-{spec.texture}-s{seed}"
            yield CalibrationPhoto("studio", name, _save(folder, name, rgb), (truth,))
    for delta_e in DELTA_ES:
        for i, shape in enumerate(SHAPES):
            for seed in (1, 2, 3, 4):
                rgb, truth = white_on_white_photo(delta_e, 100 * delta_e + 10 * i + seed, shape)
                name = f"white-dE{delta_e}-{shape}-s{seed}"
                yield CalibrationPhoto("white", name, _save(folder, name, rgb), (truth,))
    for parts in PART_COUNTS:
        for j, gap in enumerate(GAPS_PX):
            for seed in (1, 2):
                background = BACKGROUNDS[(j + seed) % len(BACKGROUNDS)]
                rgb, truths = multipart_photo(parts, gap, 1000 * parts + 10 * gap + seed, background)
                name = f"parts{parts}-gap{gap}-{background}-s{seed}"
                yield CalibrationPhoto("multipart", name, _save(folder, name, rgb), tuple(truths))
    skimage_dir = Path(skimage.data.__file__).parent
    mpl_dir = Path(matplotlib.get_data_path()) / "sample_data"
    real = sorted(p for p in skimage_dir.iterdir() if p.suffix in (".png", ".jpg") and "GRAY" not in p.name)
    real += sorted(p for p in mpl_dir.iterdir() if p.suffix in (".png", ".jpg"))
    for path in real:
        truth = None
        if path.name == "horse.png":  # a silhouette drawing: its dark pixels are the exact mask
            truth = (np.asarray(Image.open(path).convert("L")) < 128,)
        yield CalibrationPhoto("real", path.name, path, truth)
    for path in sorted((ROOT / "examples" / "photos").glob("*.jpg")):
        yield CalibrationPhoto("example", path.name, path, None)


def evaluate(segmenter: Segmenter, photo: CalibrationPhoto) -> dict:
    start = time.perf_counter()
    row: dict = {"group": photo.group, "name": photo.name}
    try:
        result = segmenter.segment(load_photo(photo.path))
    except PreparationError as exc:
        row.update(outcome="error", error=type(exc).__name__, detail=exc.reason,
                   seconds=round(time.perf_counter() - start, 3))
        if photo.parts is not None:  # no mask: nothing of the truth found
            row.update(iou=0.0, parts=len(photo.parts), parts_kept=0)
        return row
    row["seconds"] = round(time.perf_counter() - start, 3)
    row.update(outcome="warning" if result.warnings else "ok", method=result.method,
               detail="; ".join(result.warnings))
    confidence = getattr(result, "confidence", None)  # absent in runs of the code before mask confidence
    if confidence is not None:
        row["confidence"] = round(confidence.score, 3)
    if photo.parts is not None:
        mask = result.alpha >= 0.5
        truth = np.any(np.stack(photo.parts), axis=0)
        row["iou"] = round(iou(mask, truth), 4)
        row["parts"] = len(photo.parts)
        row["parts_kept"] = sum(int((mask & p).sum() >= 0.9 * p.sum()) for p in photo.parts)
    return row


def segmentation_rows() -> list[dict]:
    segmenter = Segmenter(SegmentConfig(use_rembg=False))
    with tempfile.TemporaryDirectory() as tmp:
        return [evaluate(segmenter, photo) for photo in calibration_photos(Path(tmp))]


def hf_ratios(per_cell: int) -> dict[str, list[float]]:
    cutoff = PlanConfig().hf_cutoff
    out: dict[str, list[float]] = {t: [] for t in TEXTURES}
    for texture in TEXTURES:
        for i, (shape, bg) in enumerate((s, b) for s in SHAPES for b in BACKGROUNDS):
            for k in range(per_cell):
                rgb, truth = product_photo(PhotoSpec(shape, bg, texture, 500 + 37 * i + k, size=512))
                ref = recentre(rgb.astype(np.float32) / 255.0, truth.astype(np.float32), bbox(truth), MEASURE_SIZE, 0.1)
                out[texture].append(round(object_high_frequency_ratio(ref.rgb, ref.alpha, cutoff), 5))
    return out


def timing() -> dict[str, float]:
    seg = Segmenter(SegmentConfig(use_rembg=False))
    times = {}
    with tempfile.TemporaryDirectory() as tmp:
        for photo in sorted((ROOT / "examples" / "photos").glob("*.jpg")):
            start = time.perf_counter()
            prepare_reference(photo, Path(tmp) / photo.stem, segmenter=seg)
            times[photo.name] = round(time.perf_counter() - start, 3)
    return times


def _iou_text(rows: list[dict]) -> str:
    ious = [r.get("iou", 0.0) for r in rows]  # an error has no mask: IoU 0
    return f"{min(ious):.3f} / {np.mean(ious):.3f}"


def _outcomes(rows: list[dict]) -> str:
    counts = {k: sum(r["outcome"] == k for r in rows) for k in ("ok", "warning", "error")}
    return " ".join(f"{k} {v}" for k, v in counts.items() if v)


def _kept(rows: list[dict]) -> str:
    return f"{sum(r.get('parts_kept', 0) for r in rows)}/{sum(r.get('parts', 0) for r in rows)}"


def _grouped(rows: list[dict], before: dict[str, dict], key, label: str, keys) -> list[str]:
    lines = [f"| {label} | photos | IoU min / mean (before) | IoU min / mean (after) | parts kept before → after "
             "| outcomes before → after |", "|---|---|---|---|---|---|"]
    for k in keys:
        now = [r for r in rows if key(r) == k]
        # Rows of an older run that failed carry no truth counts: the truth is the same photo's.
        old = [{"iou": 0.0, "parts": r.get("parts", 0), "parts_kept": 0, **before[r["name"]]}
               for r in now if r["name"] in before]
        old_iou, old_kept, old_out = (_iou_text(old), _kept(old), _outcomes(old)) if old else ("–", "–", "–")
        lines.append(f"| {k} | {len(now)} | {old_iou} | {_iou_text(now)} | {old_kept} → {_kept(now)} | "
                     f"{old_out} → {_outcomes(now)} |")
    return lines


def segmentation_markdown(rows: list[dict], before: dict[str, dict]) -> list[str]:
    studio = [r for r in rows if r["group"] == "studio"]
    worse = [r for r in studio if r["name"] in before and r.get("iou", 0) < before[r["name"]].get("iou", 0) - 0.005]
    lines = ["## Segmentation (classical chain, no rembg model)", ""]
    lines += _grouped(rows, before, lambda r: r["group"], "set", ("studio", "white", "multipart"))
    lines += ["", f"Studio photos whose IoU dropped by more than 0.005: {len(worse)}"
              + (" (" + ", ".join(f"{r['name']} {before[r['name']]['iou']:.3f} → {r.get('iou', 0):.3f}"
                                   for r in worse) + ")" if worse else "") + ".", ""]
    lines += ["White product on a white backdrop, by ΔE between them (4 shapes × 4 seeds each):", ""]
    lines += _grouped(rows, before, lambda r: int(r["name"].split("-")[1][2:]) if r["group"] == "white" else None,
                      "ΔE", DELTA_ES)
    lines += ["", "Separate parts, by number of parts and gap (2 seeds each, backgrounds cycling):", ""]
    lines += _grouped(rows, before, lambda r: r["name"].rsplit("-", 2)[0] if r["group"] == "multipart" else None,
                      "parts-gap", [f"parts{p}-gap{g}" for p in PART_COUNTS for g in GAPS_PX])
    lines += ["", "Real photographs (packages' sample data) and the bundled examples:", "",
              "| photo | cluttered | outcome before | outcome after | confidence | IoU | detail |",
              "|---|---|---|---|---|---|---|"]
    for r in rows:
        if r["group"] in ("real", "example"):
            old = before.get(r["name"], {})
            lines.append(f"| {r['name']} | {'yes' if r['name'] in CLUTTERED else ''} | {old.get('outcome', '–')} | "
                         f"{r['outcome']} | {r.get('confidence', '–')} | {r.get('iou', '')} | "
                         f"{r.get('detail', '')[:140]} |")
    seconds = [r["seconds"] for r in rows]
    lines += ["", f"Segmentation time per photo (this machine, 2 cores): median {np.median(seconds):.3f} s, "
              f"max {max(seconds):.3f} s over {len(rows)} photos.", ""]
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    parser.add_argument("--before", type=Path, help="an earlier --segmentation-only JSON to compare with")
    parser.add_argument("--segmentation-only", action="store_true")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = segmentation_rows()
    if args.segmentation_only:
        (args.out / "prepare_calibration_segmentation.json").write_text(json.dumps(rows, indent=2))
        return
    before = {r["name"]: r for r in json.loads(args.before.read_text())} if args.before else {}
    hf = hf_ratios(per_cell=2)
    times = timing()
    flat_max = max(hf["flat"])
    textured_min = min(v for t, vals in hf.items() if t != "flat" for v in vals)
    plan = PlanConfig()
    result = {"date": time.strftime("%Y-%m-%d"), "segmentation": rows, "segmentation_before": list(before.values()),
              "hf_ratio": hf, "hf_cutoff": plan.hf_cutoff, "hf_threshold": plan.hf_threshold,
              "flat_max": flat_max, "textured_min": textured_min, "prepare_seconds": times}
    (args.out / "prepare_calibration.json").write_text(json.dumps(result, indent=2))
    lines = ["# Reference preparation: calibration and measurements", "",
             f"{result['date']}, `.venv/bin/python -m benchmarks.prepare_calibration"
             + (f" --before {args.before}`" if args.before else "`") + " (CPU, 2 cores).", ""]
    lines += segmentation_markdown(rows, before)
    lines += [
        f"## High-frequency ratio of the object interior above {plan.hf_cutoff}·Nyquist "
        f"(256-px reference, {len(hf['flat'])} photos per texture)", "",
        "| texture | min | median | max |",
        "|---|---|---|---|",
    ]
    lines += [f"| {t} | {min(v):.4f} | {np.median(v):.4f} | {max(v):.4f} |" for t, v in hf.items()]
    lines += [
        "",
        f"Flat max {flat_max:.4f}, textured min {textured_min:.4f}; threshold {plan.hf_threshold} sits "
        "between them (near their geometric mean).",
        "",
        "prepare_reference at default settings (classical chain, 512-px photos, this machine): "
        + ", ".join(f"{k} {v:.2f} s" for k, v in times.items()),
    ]
    (args.out / "prepare_calibration.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
