"""Run the real pipeline on a synthetic scene's photo with the oracle priors, and time each stage."""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import torch

from assets_store.runlog import read_runlog
from assets_store.store import Store
from benchmarks.oracle import OracleConfig, oracle_suites
from benchmarks.scenes import FRAME_FILL, Scene
from ops.config.presets import PipelineConfig, preset, with_steps
from ops.engine.artifacts import RUNLOG_FILE
from ops.engine.config_tree import apply_overrides
from ops.pipeline.photo_run import PhotoOutcome
from ops.pipeline.runner import Pipeline, stages_until

log = logging.getLogger("morpheus3d.bench")

PHOTO_SIZE = 512


@dataclass(frozen=True)
class Schedule:
    """A pipeline configuration by name: a preset, optionally its steps replaced, plus overrides."""

    label: str
    preset: str
    steps: tuple[int, int, int] | None = None
    overrides: tuple[str, ...] = ()

    def config(self, device: str, extra: Iterable[str] = ()) -> PipelineConfig:
        cfg = preset(self.preset)
        if self.steps is not None:
            cfg = with_steps(cfg, *self.steps)
        return apply_overrides(cfg, (*self.overrides, f"device={device}", *extra))


def schedule_store(work: Path, schedule: Schedule) -> Store:
    """Each schedule's own store under ``work`` (labels such as ``standard/5`` made path-safe)."""
    return Store(Path(work) / ("store_" + schedule.label.replace("/", "-")))


def photo_path(scene: Scene, folder: Path, fill: float = FRAME_FILL) -> Path:
    """The scene's product photo (written once; the name carries the framing)."""
    suffix = "" if fill == FRAME_FILL else f"_fill{fill:g}"
    path = Path(folder) / f"{scene.name}_s{scene.seed}{suffix}.png"
    if not path.is_file():
        scene.write_photo(path, PHOTO_SIZE, fill)
    return path


def run_scene(scene: Scene, photo: Path, store: Store, cfg: PipelineConfig, label: str, key: str,
              until: str, oracle: OracleConfig | None = None) -> PhotoOutcome:
    """The pipeline with the oracle priors up to ``until``; stages already in the store are reused."""
    device = torch.device("cuda" if cfg.device in ("auto", "cuda") and torch.cuda.is_available() else "cpu")
    suites = oracle_suites(scene, cfg, device, oracle)
    out = Pipeline(store, cfg, label, suites=suites).run([(photo, key)], stages_until(until))[0]
    if out.error:
        log.warning("%s (%s): %s", key, label, out.error)
    return out


def stage_wall_s(store: Store, key: str, stage: str) -> float:
    """Wall time the stage took when it ran (from its manifest: a cached stage keeps its time)."""
    manifest = store.read_manifest(key, stage)
    if manifest is None:
        raise FileNotFoundError(f"{key}/{stage}: no finished output to time")
    return float(manifest.wall_time_s)


def stage_guards(store: Store, key: str, stage: str) -> dict[str, int]:
    manifest = store.read_manifest(key, stage)
    metrics = manifest.metrics if manifest is not None else {}
    return {k[len("guard_"):]: int(v) for k, v in metrics.items() if k.startswith("guard_")}


def runlog_curve(store: Store, key: str, stage: str) -> list[tuple[float, float]]:
    """(seconds into the stage, reference-view PSNR) from the stage's log."""
    path = store.stage_dir(key, stage) / RUNLOG_FILE
    if not path.is_file():
        return []
    return [(float(r["wall_s"]), float(r["ref_psnr"])) for r in read_runlog(path)
            if r.get("ref_psnr") is not None and r.get("wall_s") is not None]
