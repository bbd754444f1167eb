"""Per-scene stage plan: what this reference needs from the later stages, and why.

Written as ``plan.json`` beside ``reference.json``; later stages read it instead of guessing.
Every decision carries a reason and the measurements behind it, and skipped stages are listed.

Rules (calibration in ``benchmarks/results/prepare_calibration.md``):
- segmentation: skipped when the photo's own alpha channel gave the mask.
- high-pass 2D-prior texture refinement: skipped when the object's interior has little energy in
  the band that refinement acts on. The paper's filter keeps DCT indices ≥ r·D of the 64×64
  latent of a 512 render (r = 0.6), i.e. frequencies above ≈ r·64/256 = 0.15 of the 256-px
  reference's Nyquist; we measure the share of energy there (windowed interior, see
  ``object_high_frequency_ratio``). Generated flat objects measured ≤ 0.054, printed/grained/
  striped ones ≥ 0.11; the threshold 0.08 sits near their geometric mean.
- DMTet grid: the largest step of ``grid_step`` in [min_grid, max_grid] that (a) does not resolve
  finer than the photo shows — at least ``source_px_per_cell`` source pixels per cell across the
  object — and (b) keeps the extracted surface under ``extract_face_limit``. The face count comes
  from DMTet's own estimate (``morpheus_core.geometry.tet_surface.estimate_faces``, ≈ 9 faces per cell²
  of surface), with the surface taken as ``surface_per_silhouette`` × the silhouette's area: Cauchy's
  formula gives 4 × the mean projected area for a convex body. Larger objects in the source photo
  get finer grids; bulky silhouettes are capped by the face limit.
- export: meshes above ``export_max_faces`` (xatlas slows super-linearly) are marked for decimation.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from assets_store.atomic import atomic_write_text
from morpheus_core.geometry.tet_surface import estimate_faces, suggest_resolution
from morpheus_core.imaging import object_high_frequency_ratio, resize
from ops.intake.prepare import ReferenceInfo, read_reference

PLAN_FILE = "plan.json"
SCHEMA = 1
MEASURE_SIZE = 256  # the calibration below holds for the 256-px reference


@dataclass(frozen=True)
class PlanConfig:
    hf_cutoff: float = 0.15
    """Share of Nyquist where the paper's high-pass band (r = 0.6) starts at 256 px: energy above it is measured."""
    hf_threshold: float = 0.08
    """High-frequency energy share below which texture refinement is skipped (flat ≤ 0.054, detailed ≥ 0.11)."""
    min_grid: int = 64
    """Smallest DMTet grid (cells per side) the plan picks, even when detail or face limits ask for less."""
    max_grid: int = 128
    """Largest DMTet grid (cells per side) the plan picks; 128 is the paper's grid."""
    grid_step: int = 16
    """The planned DMTet grid is a multiple of this (rounded down)."""
    source_px_per_cell: float = 2.0
    """Least source-photo pixels per grid cell across the object: no finer grid than the photo resolves."""
    surface_per_silhouette: float = 4.0
    """Surface area estimate as a multiple of the silhouette area (Cauchy: 4 × mean projection, convex bodies)."""
    extract_face_limit: int = 250_000
    """The grid is capped so the estimated extracted surface (≈ 9 faces per cell² of surface) stays below this."""
    export_max_faces: int = 50_000
    """Estimated face count above which the plan marks the mesh for decimation before UV unwrapping (xatlas)."""
    frame_in_grid: float = 2 * 2.5 * math.tan(math.radians(20.0)) / 2.0
    """Share of the 2-unit grid cube the reference view spans: distance 2.5, fov 40° see 2·2.5·tan 20° = 1.82 units."""


@dataclass(frozen=True)
class Decision:
    action: str  # "run" | "skip" | "set"
    value: Any
    reason: str
    measurements: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class StagePlan:
    source_sha256: str
    segmentation: Decision
    highpass_refinement: Decision
    dmtet_grid: Decision
    export: Decision
    config: dict[str, Any]
    schema: int = SCHEMA

    @property
    def skipped(self) -> list[str]:
        return [name for name in ("segmentation", "highpass_refinement") if getattr(self, name).action == "skip"]

    def summary(self) -> str:
        refine = "skip refine" if self.highpass_refinement.action == "skip" else "refine"
        return f"grid {self.dmtet_grid.value}, {refine}"

    def to_json(self) -> str:
        data = asdict(self)
        data["skipped"] = self.skipped
        return json.dumps(data, indent=2, sort_keys=True, allow_nan=False, ensure_ascii=False)

    @classmethod
    def from_json(cls, text: str) -> StagePlan:
        data = json.loads(text)
        data.pop("skipped", None)
        if data.get("schema") != SCHEMA:
            raise ValueError(f"plan schema {data.get('schema')!r}, expected {SCHEMA}")
        for key in ("segmentation", "highpass_refinement", "dmtet_grid", "export"):
            data[key] = Decision(**data[key])
        return cls(**data)


def _segmentation(info: ReferenceInfo) -> Decision:
    if info.method == "alpha":
        return Decision("skip", "alpha", "the photo's own alpha channel is the mask; no segmentation needed")
    how = f"u2net model {info.model_path}" if info.method == "rembg" else "classical border-colour + GrabCut chain"
    score = float(info.confidence["score"])
    return Decision("run", info.method, f"mask segmented with the {how}: {info.kept_parts} part(s), "
                    f"confidence {score:.2f}", {"parts": info.kept_parts, "confidence": score})


def _refinement(rgb: np.ndarray, alpha: np.ndarray, cfg: PlanConfig) -> Decision:
    ratio = object_high_frequency_ratio(rgb, alpha, cfg.hf_cutoff)
    m = {"hf_ratio": round(ratio, 5), "hf_cutoff": cfg.hf_cutoff, "hf_threshold": cfg.hf_threshold}
    if ratio < cfg.hf_threshold:
        return Decision("skip", False, f"object interior has {ratio:.3f} of its energy above {cfg.hf_cutoff:g}·Nyquist "
                        f"(< {cfg.hf_threshold:g}): flat texture, the high-pass 2D prior has nothing to add", m)
    return Decision("run", True, f"object interior has {ratio:.3f} of its energy above {cfg.hf_cutoff:g}·Nyquist "
                    f"(≥ {cfg.hf_threshold:g}): fine detail for the high-pass 2D prior to refine", m)


def _grid(info: ReferenceInfo, area_fraction: float, cfg: PlanConfig) -> tuple[Decision, float]:
    span = (1.0 - 2.0 * info.border_ratio) * cfg.frame_in_grid  # object's long side / grid side
    grid_area = area_fraction * cfg.frame_in_grid**2  # silhouette share of a grid face
    surface = max(cfg.surface_per_silhouette * grid_area * 4.0, 1e-9)  # world units²: the grid face is 2 × 2
    n_detail = info.object_long_side_px / (cfg.source_px_per_cell * span)
    n_faces = suggest_resolution(cfg.extract_face_limit, surface, min_resolution=1, max_resolution=1 << 16)
    limit = min(n_detail, n_faces, cfg.max_grid)
    n = max(cfg.min_grid, int(limit // cfg.grid_step) * cfg.grid_step)
    faces = estimate_faces(n, surface)
    binding = {n_detail: "source detail", n_faces: "extracted face limit", cfg.max_grid: "max_grid"}[limit]
    m = {"object_long_side_px": info.object_long_side_px, "silhouette_share": round(area_fraction, 4),
         "grid_by_detail": round(n_detail, 1), "grid_by_faces": round(n_faces, 1), "estimated_faces": round(faces)}
    reason = (f"object spans {info.object_long_side_px} source px and {area_fraction:.0%} of the reference; "
              f"limited by {binding} ({limit:.0f}) → grid {n}, ≈{faces / 1000:.0f}k extracted faces")
    if n == cfg.min_grid and limit < cfg.min_grid:
        reason += f" (raised to min_grid {cfg.min_grid})"
    return Decision("set", n, reason, m), faces


def _export(faces: float, cfg: PlanConfig) -> Decision:
    m = {"estimated_faces": round(faces)}
    if faces > cfg.export_max_faces:
        return Decision("set", cfg.export_max_faces, f"≈{faces / 1000:.0f}k extracted faces > {cfg.export_max_faces} "
                        "(xatlas slows super-linearly): decimate before UV unwrapping", m)
    return Decision("set", None, f"≈{faces / 1000:.0f}k extracted faces: no decimation needed", m)


def make_plan(info: ReferenceInfo, rgba: np.ndarray, cfg: PlanConfig | None = None) -> StagePlan:
    """The plan for a reference from its metadata and its RGBA image (uint8, any square size)."""
    cfg = cfg or PlanConfig()
    rgba = rgba.astype(np.float32) / 255.0
    if rgba.shape[0] != MEASURE_SIZE:
        rgba = resize(rgba, (MEASURE_SIZE, MEASURE_SIZE))
    rgb, alpha = rgba[..., :3], rgba[..., 3]
    grid, faces = _grid(info, float((alpha >= 0.5).mean()), cfg)
    return StagePlan(info.source_sha256, _segmentation(info), _refinement(rgb, alpha, cfg), grid,
                     _export(faces, cfg), asdict(cfg))


def plan_reference(folder: Path | str, cfg: PlanConfig | None = None) -> StagePlan:
    """Plan a prepared reference folder and write ``plan.json`` there atomically."""
    folder = Path(folder)
    info = read_reference(folder)
    if info is None:
        raise FileNotFoundError(f"{folder}: no valid {folder / 'reference.json'}; run `morpheus3d prepare` first")
    key = f"rgba_{MEASURE_SIZE}" if f"rgba_{MEASURE_SIZE}" in info.files else max(info.files, key=_size_of)
    rgba = np.asarray(Image.open(folder / info.files[key]).convert("RGBA"))
    plan = make_plan(info, rgba, cfg)
    atomic_write_text(folder / PLAN_FILE, plan.to_json())
    return plan


def read_plan(folder: Path | str) -> StagePlan | None:
    try:
        return StagePlan.from_json((Path(folder) / PLAN_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError, TypeError, KeyError):
        return None


def _size_of(key: str) -> int:
    return int(key.rsplit("_", 1)[1]) if key.startswith("rgba_") else -1
