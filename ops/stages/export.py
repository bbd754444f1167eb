"""The catalog export: the baked asset at its real size as GLB, a web-sized GLB and USDZ, each checked by
its format's own validator.

Product pages and "view in your room" place a model at its real size: Android and the web read GLB, iOS
AR Quick Look only USDZ. The bake's ``asset.glb`` stays in the method's normalised frame (what QA renders);
this stage scales it to metres from the product's catalog size (``products.csv`` beside the photos,
``ops.intake.products``, or ``export.height_mm`` etc. in the run's config, which win), puts the origin at
the bottom centre (+Y up, front +Z: ``morpheus_core.export.true_size``) and writes:

- ``model.glb``: true size, the bake's full texture (PNG), for editing;
- ``model.web.glb``: the same within ``export.web_budget_bytes`` (WebP texture, quantised and compressed
  geometry: ``morpheus_core.export.web_glb``), for product pages;
- ``model.usdz``: the same mesh and texture as a ``UsdPreviewSurface`` (``morpheus_core.export.usdz``);
- ``size.png``: the front and side silhouettes with their dimensions in millimetres (the preview: a wrong
  size shows at a glance).

Without a size the asset gets ``export.default_height_mm`` and ``scale_source: "default"`` in its metrics
(and the catalog). Both GLBs go through the Khronos glTF-Validator (``make web-tools`` installs it; without
Node.js the check is recorded as not run) and the USDZ through USD's ARKit compliance checker; the ``qa``
stage fails an asset whose files do not validate (the ``formats_valid`` check).
"""

from __future__ import annotations

import io
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from assets_store.atomic import atomic_write_bytes
from morpheus_core.export.gltf import decode_glb, export_glb
from morpheus_core.export.gltf_validator import validate_gltf, validator_available
from morpheus_core.export.true_size import fit_true_size
from morpheus_core.export.usdz import check_usdz, export_usdz
from morpheus_core.export.web_glb import write_web_glb
from ops.engine.checks import ERROR, WARN, CheckSpec, CheckThresholds, QACheck, check
from ops.engine.stage import Stage, StageContext, StageWork
from ops.engine.stage_job import StageResult
from ops.intake.products import DIMENSIONS, ProductSize, positive_mm, products_for
from ops.stages.bake import ASSET_GLB

MODEL_GLB = "model.glb"
MODEL_WEB_GLB = "model.web.glb"
MODEL_USDZ = "model.usdz"
SIZE_CARD = "size.png"
CODE_VERSION = "export-1"


@dataclass(frozen=True)
class ExportStageConfig:
    """True size, web budget and formats of the catalog export. ``height_mm`` / ``width_mm`` / ``depth_mm``
    set the size for this run (Dagster run config, ``--set export.height_mm=250``) instead of ``products.csv``."""

    height_mm: float | None = None
    """The product's true height (mm); wins over ``products.csv``. Scaled by height, else width, else depth."""
    width_mm: float | None = None
    """The product's true width (mm, along the photo's left-right axis)."""
    depth_mm: float | None = None
    """The product's true depth (mm, front to back)."""
    default_height_mm: float = 200.0
    """Height (mm) of an asset whose size nobody gave (recorded as ``scale_source: default``)."""
    web_budget_bytes: int = 3_000_000
    """Size limit (bytes) of ``model.web.glb``: WebP quality, then texture size, go down until it fits."""
    usdz: bool = True
    """Also write ``model.usdz`` (AR Quick Look)."""
    validate: bool = True
    """Run the glTF validator and USD's compliance checker on what was written."""

    def __post_init__(self) -> None:
        for name in (*DIMENSIONS, "default_height_mm"):
            positive_mm(f"export.{name}", getattr(self, name))
        if self.web_budget_bytes <= 0:
            raise ValueError(f"export.web_budget_bytes must be positive, got {self.web_budget_bytes}")


def product_size(photo: Path, cfg: ExportStageConfig) -> ProductSize | None:
    """The photo's size: the run's config when it gives one, else its ``products.csv`` row, else None.
    A bad row for this photo raises ``ProductsFileError`` naming the file and line."""
    if any(getattr(cfg, d) is not None for d in DIMENSIONS):
        return ProductSize(photo.name, "", cfg.height_mm, cfg.width_mm, cfg.depth_mm, source="config")
    table = products_for(photo)
    size = table.size_of(photo.name) if table is not None else None
    return size if size is not None and size.given else None


def export_asset(bake_dir: Path, out_dir: Path, cfg: ExportStageConfig, size: ProductSize | None,
                 name: str) -> StageResult:
    """Size the bake's GLB and write the three files, validated; metrics: where the size came from, the size
    in millimetres, any disagreement of the other given dimensions, file sizes, validator results."""
    baked = decode_glb((Path(bake_dir) / ASSET_GLB).read_bytes())
    if size is None:
        known = {"height": cfg.default_height_mm / 1000}
        source = "default"
    else:
        mm = {d.removesuffix("_mm"): getattr(size, d) for d in DIMENSIONS}
        known = {d: v / 1000 if v is not None else None for d, v in mm.items()}
        source = size.source
    sized, fit = fit_true_size(baked, known)
    notes = []
    if size is None:
        notes.append(f"no size given (products.csv or export.height_mm): {cfg.default_height_mm:g} mm tall by default")
    for dim, off in fit.disagreement.items():
        notes.append(f"{dim}: the mesh is {fit.size_m[dim] * 1000:.0f} mm at the size set by its {fit.scaled_by}, "
                     f"the catalog says {known[dim] * 1000:.0f} mm ({off:.0%} apart)")
    out_dir = Path(out_dir)
    export_glb(sized, out_dir / MODEL_GLB)
    save_size_card(out_dir / SIZE_CARD, sized.vertices, sized.faces)
    web = write_web_glb(sized, out_dir / MODEL_WEB_GLB, cfg.web_budget_bytes)
    if cfg.usdz:
        export_usdz(sized, out_dir / MODEL_USDZ, name=name)
    metrics: dict[str, Any] = {
        "scale_source": source, "scaled_by": fit.scaled_by, "sku": size.sku if size is not None else "",
        **{f"{d}_mm": round(m * 1000, 2) for d, m in fit.size_m.items()},
        "size_disagreement": round(fit.worst(), 4),
        "glb_bytes": (out_dir / MODEL_GLB).stat().st_size, "web_glb_bytes": web.total_bytes,
        "web_budget_bytes": cfg.web_budget_bytes, "web_texture_size": web.texture_size,
        "web_webp_quality": web.webp_quality, "web_extensions": list(web.extensions),
    }
    if cfg.usdz:
        metrics["usdz_bytes"] = (out_dir / MODEL_USDZ).stat().st_size
    if cfg.validate:
        metrics.update(validation_metrics(out_dir, cfg.usdz))
    return StageResult(metrics, "none (export)", "cpu", notes)


def save_size_card(path: Path, vertices: np.ndarray, faces: np.ndarray, size: int = 256) -> Path:
    """A PNG of the front (x, y) and side (z, y) silhouettes on one scale, each with its width and the
    height written beside it in millimetres."""
    v = np.asarray(vertices, np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    span = float((hi - lo).max()) or 1.0
    margin = 40
    scale = (size - 2 * margin) / span
    font = ImageFont.load_default(size=14)
    panels = []
    for axis, label in ((0, "front"), (2, "side")):
        img = Image.new("RGB", (size, size), "white")
        draw = ImageDraw.Draw(img)
        # Image x from the horizontal axis, image y downward from the top of the object.
        px = (v[:, axis] - (lo[axis] + hi[axis]) / 2) * scale + size / 2
        py = size - margin - (v[:, 1] - lo[1]) * scale
        for tri in np.stack([px, py], axis=1)[faces]:
            draw.polygon([tuple(p) for p in tri], fill=(150, 160, 175))
        left, right = size / 2 - (hi[axis] - lo[axis]) * scale / 2, size / 2 + (hi[axis] - lo[axis]) * scale / 2
        top, bottom = size - margin - (hi[1] - lo[1]) * scale, size - margin
        draw.line([(left, bottom + 12), (right, bottom + 12)], fill="black")
        draw.text((size / 2, bottom + 14), f"{(hi[axis] - lo[axis]) * 1000:.0f} mm", fill="black", font=font,
                  anchor="mt")
        draw.line([(right + 12, top), (right + 12, bottom)], fill="black")
        draw.text((right + 14, (top + bottom) / 2), f"{(hi[1] - lo[1]) * 1000:.0f}", fill="black", font=font,
                  anchor="lm")
        draw.text((6, 6), label, fill="black", font=font)
        panels.append(np.asarray(img))
    buf = io.BytesIO()
    Image.fromarray(np.concatenate(panels, axis=1)).save(buf, format="PNG")
    return atomic_write_bytes(path, buf.getvalue())


def validation_metrics(out_dir: Path, usdz: bool) -> dict[str, Any]:
    """Errors and warnings of each written file by its format's validator; ``gltf_validator`` says why the
    glTF validator did not run where it could not (the check then reads as not run, not as passed)."""
    out: dict[str, Any] = {}
    missing = validator_available()
    out["gltf_validator"] = missing or "ran"
    if missing is None:
        for key, file in (("glb", MODEL_GLB), ("web_glb", MODEL_WEB_GLB)):
            report = validate_gltf(out_dir / file)
            out[f"{key}_errors"], out[f"{key}_warnings"] = report.errors, report.warnings
            out[f"{key}_messages"] = [f"{m.code}: {m.message} ({m.pointer})" for m in report.messages][:10]
    if usdz:
        check = check_usdz(out_dir / MODEL_USDZ)
        out["usdz_errors"], out["usdz_warnings"] = len(check.errors), len(check.warnings)
        out["usdz_messages"] = [*check.errors, *check.warnings][:10]
    return out


def _build(ctx: StageContext, cfg: ExportStageConfig) -> StageWork:
    size = product_size(ctx.photo, cfg)
    name = (size.sku if size is not None and size.sku else "") or ctx.key

    def body(out: Path, _ckpt: Path | None) -> StageResult:
        return export_asset(ctx.dir("bake"), out, cfg, size, name)

    # The size decides the output, so it is part of the fingerprint (a corrected row re-exports); the line it
    # came from is not (moving a row changes nothing).
    product = replace(size, source="") if size is not None else None
    return StageWork({"export": cfg, "product": product}, body)


FORMATS_VALID = CheckSpec("formats_valid", ERROR, "the true-size GLB, the web GLB and the USDZ pass their formats' "
                                                  "validators (glTF-Validator, USD's ARKit checks) with 0 errors; a "
                                                  "warning where a validator could not run")
TRUE_SIZE = CheckSpec("true_size", WARN, "the size comes from the catalog (products.csv or export.*_mm) and its other "
                                         "dimensions agree with the mesh within qa.max_size_disagreement")


def _judge(metrics: dict[str, Any], cfg: CheckThresholds) -> list[QACheck]:
    return [_formats_valid(metrics), _true_size(metrics, cfg)]


def _formats_valid(metrics: dict[str, Any]) -> QACheck:
    """Errors of every validated file; a validator that did not run makes this a warning, not a pass."""
    errors = {k.removesuffix("_errors"): int(v) for k, v in metrics.items() if k.endswith("_errors") and v}
    counted = [k for k in metrics if k.endswith("_errors")]
    if errors:
        detail = "; ".join(str(m) for k in errors for m in metrics.get(f"{k}_messages", [])[:3])
        return check(FORMATS_VALID, False, sum(errors.values()), 0,
                     f"validator errors in {', '.join(f'{k} ({n})' for k, n in errors.items())}: {detail}")
    missing = metrics.get("gltf_validator", "not run")
    if missing != "ran" or not counted:
        return check(FORMATS_VALID, False, None, 0, f"not validated: {missing}", severity=WARN)
    return check(FORMATS_VALID, True, 0, 0, f"0 errors in {', '.join(k.removesuffix('_errors') for k in counted)}")


def _true_size(metrics: dict[str, Any], cfg: CheckThresholds) -> QACheck:
    source, off = metrics.get("scale_source", "default"), float(metrics.get("size_disagreement", 0.0))
    ok = source != "default" and off <= cfg.max_size_disagreement
    allowed = cfg.max_size_disagreement
    why = ("no size in products.csv or export.height_mm: sized by export.default_height_mm" if source == "default"
           else f"sized from {source}; other dimensions {off:.0%} off the mesh (allowed {allowed:.0%})")
    return check(TRUE_SIZE, ok, round(off, 4), cfg.max_size_disagreement, why)


STAGE = Stage(
    "export", CODE_VERSION, config=ExportStageConfig, reads=("bake",),
    writes=(MODEL_GLB, MODEL_WEB_GLB, MODEL_USDZ, SIZE_CARD),
    preview=SIZE_CARD, gpu=False, build=_build, checks=(FORMATS_VALID, TRUE_SIZE), judge=_judge,
    description="The asset at its real size: GLB, web-sized GLB and USDZ, checked by the formats' validators.")
