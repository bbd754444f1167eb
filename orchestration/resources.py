"""The resource every asset, sensor and schedule reads: where photos and the store are, and the
pipeline configuration (a preset plus ``key=value`` overrides, the same as ``morpheus3d run``)."""

from __future__ import annotations

from pathlib import Path

from dagster import ConfigurableResource
from pydantic import Field

from assets_store.catalog import Catalog
from assets_store.photo_hashes import PhotoHashes
from assets_store.store import Store
from ops.config.presets import PipelineConfig, preset
from ops.engine.progress import ProgressFn
from ops.engine.store_layout import open_store
from ops.intake import photo_folder
from ops.pipeline.photo_run import StageOutcome
from ops.pipeline.runner import Pipeline
from ops.reporting.catalog_rows import photo_row


class UnknownPhotoError(LookupError):
    """A partition whose photo is no longer in the watched folder."""


class MorpheusResource(ConfigurableResource):
    photo_dir: str
    store_root: str
    preset: str = "draft"
    overrides: list[str] = Field(default_factory=list)
    settle_seconds: float = 30.0

    def pipeline_config(self) -> PipelineConfig:
        return preset(self.preset, self.overrides)

    def store(self) -> Store:
        return open_store(self.store_root)

    def pipeline(self, progress: ProgressFn | None = None) -> Pipeline:
        return Pipeline(self.store(), self.pipeline_config(), self.preset, progress=progress)

    def photos(self) -> dict[str, str]:
        """Photo key → file name in the watched folder."""
        return photo_folder.scan(Path(self.photo_dir))

    def photo_path(self, key: str, photos: dict[str, str] | None = None) -> Path:
        names = self.photos() if photos is None else photos
        if key not in names:
            raise UnknownPhotoError(f"partition {key!r} has no photo in {self.photo_dir} (renamed or removed?); "
                                    "put the photo back or delete the partition")
        return Path(self.photo_dir) / names[key]

    def run_stage(self, key: str, stage: str, progress: ProgressFn | None = None) -> StageOutcome:
        """``stage`` for one photo, reading its inputs from the store; raises what stopped it (so the
        orchestrator can retry: finished outputs and checkpoints stay in place)."""
        outcome = self.pipeline(progress).run([(self.photo_path(key), key)], [stage])[0]
        if outcome.exception is not None:
            raise outcome.exception
        return outcome.stages[-1]

    def run_stage_batch(self, keys: list[str], stage: str,
                        progress: ProgressFn | None = None) -> dict[str, StageOutcome | Exception]:
        """``stage`` for several photos together (``Pipeline.run``: one batch for those that optimise); per key
        its outcome or the exception that stopped it (``UnknownPhotoError`` for a photo gone from the folder)."""
        names = self.photos()
        out: dict[str, StageOutcome | Exception] = {}
        present = []
        for key in keys:
            try:
                present.append((self.photo_path(key, names), key))
            except UnknownPhotoError as exc:
                out[key] = exc
        for outcome in self.pipeline(progress).run(present, [stage]) if present else ():
            out[outcome.key] = outcome.exception if outcome.exception is not None else outcome.stages[-1]
        return {key: out[key] for key in keys}

    def record(self, key: str, run_id: str, statuses: dict[str, str], failure: str | None = None) -> None:
        """Append this photo's catalog row (after its QA, or when a stage failed for good)."""
        store = self.store()
        Catalog(store.catalog_dir).append([photo_row(store, key, run_id, statuses, failure)])

    def status(self, keys: list[str]) -> dict[str, dict[str, str]]:
        """Stage status (fresh / stale / missing) per key whose photo is present; photos are hashed
        only when they changed since the last look."""
        names, pipeline = self.photos(), self.pipeline()
        hashes, memo = PhotoHashes(self.store_root), {}
        out = {k: pipeline.status(Path(self.photo_dir) / names[k], k, hashes=hashes, memo=memo)
               for k in keys if k in names}
        hashes.save()
        return out
