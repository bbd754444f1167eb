"""One photo's run through the stages, with the store's caching, manifests and checkpoints.

For each stage the fingerprint is (the hashes of its inputs — the photo, or upstream outputs —,
the hash of its config including which priors actually run, its code version). A stage whose
fingerprint matches a finished output is skipped as cached; otherwise it runs in a staging
folder that the store commits atomically with its manifest, resuming from the newest valid
checkpoint of the same fingerprint. A failure stops this photo only, leaving every finished
stage in place for the next run.
"""

from __future__ import annotations

import json
import logging
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field, is_dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from assets_store.hashing import bytes_sha256, config_hash, file_sha256
from assets_store.manifest import Fingerprint, Manifest
from assets_store.store import StageWriter, Store
from ops.config.presets import PipelineConfig
from ops.engine.checks import CheckThresholds, QACheck
from ops.engine.config_tree import to_dict
from ops.engine.early_stop import whole_schedule_record
from ops.engine.gpu_lease import memory_hint
from ops.engine.priors import PriorsConfig, PriorSuite
from ops.engine.progress import ProgressEvent, ProgressFn
from ops.engine.stage import StageWork
from ops.engine.stage_job import StageResult
from ops.engine.store_layout import adopt_layout1_checkpoint, checkpoint_path
from ops.intake.plan import PLAN_FILE, StagePlan, read_plan
from ops.migrations import ADDED_SETTINGS
from ops.stages import BY_ID, STAGES, stage_checks

log = logging.getLogger("morpheus3d")
# The stage whose output holds the photo's plan (what the later stages are sized by).
PLANNER = next(s.id for s in STAGES if PLAN_FILE in s.writes)

@dataclass
class StageOutcome:
    stage: str
    status: str  # "ran" | "resumed" | "cached" | "skipped" | "failed"
    wall_s: float = 0.0
    manifest: Manifest | None = None
    error: str | None = None
    lease: str | None = None  # the GPU lease it ran under (``ops.engine.gpu_lease``), None on the CPU


@dataclass
class PhotoOutcome:
    photo: Path
    key: str
    stages: list[StageOutcome] = field(default_factory=list)
    error: str | None = None
    exception: Exception | None = None
    """What stopped this photo: callers classify it (bad input or transient) or raise it again."""

    @property
    def status(self) -> str:
        if self.error:
            return "failed"
        return "cached" if all(s.status in ("cached", "skipped") for s in self.stages) else "ok"

    @property
    def wall_s(self) -> float:
        return sum(s.wall_s for s in self.stages)

    def metric(self, stage: str, name: str) -> Any:
        for s in self.stages:
            if s.stage == stage and s.manifest is not None:
                return s.manifest.metrics.get(name)
        return None


def stage_config_record(config: dict[str, Any]) -> dict[str, Any]:
    """A stage's config (``StageWork.config``) as plain JSON data: what its manifest records and its
    fingerprint's config hash is of (``ADDED_SETTINGS`` at their defaults left out)."""
    record = json.loads(json.dumps(to_dict(config), default=str))
    stack = [record]
    while stack:
        node = stack.pop()
        for name, default in ADDED_SETTINGS.items():
            if name in node and node[name] == default:
                del node[name]
        stack.extend(v for v in node.values() if isinstance(v, dict))
    return record


def output_digest(manifest: Manifest) -> str:
    """One hash for a stage's whole output (every file's content hash)."""
    return bytes_sha256(repr(sorted((k, v.sha256) for k, v in manifest.outputs.items())).encode())


class MissingUpstreamError(RuntimeError):
    """A stage was asked to run before the stage it reads from has a finished output."""


@dataclass(frozen=True)
class PlannedStage:
    """A stage's work for one photo with the fingerprints that decide whether it must run.

    ``fingerprint`` is of the whole config; ``whole_schedule`` leaves the early-stopping settings
    out (``ops.engine.early_stop``): it is what an output that ran every step of its schedule is
    recorded under, and such an output satisfies any early-stopping setting. Checkpoints, made
    before any stop, are kept under it too."""

    stage: str
    work: StageWork
    fingerprint: Fingerprint
    whole_schedule: Fingerprint

    def matches(self, fingerprint: Fingerprint) -> bool:
        return fingerprint in (self.fingerprint, self.whole_schedule)

    def recorded(self, result: StageResult) -> Fingerprint:
        """The fingerprint a finished output is committed under."""
        return self.fingerprint if result.metrics.get("stopped_early") else self.whole_schedule


class PhotoRun:
    """The state of one photo's run: where things are, what upstream produced, how to report.
    It is the ``StageContext`` the stages declare their work against (``ops.engine.stage``)."""

    def __init__(self, photo: Path, key: str, store: Store, cfg: PipelineConfig, preset: str,
                 init_mesh: Path | None, progress: ProgressFn | None,
                 suites: dict[str, Callable[[], PriorSuite]] | None) -> None:
        self.photo, self.key, self.store, self.cfg, self.preset = photo, key, store, cfg, preset
        self.init_mesh = init_mesh
        self.reporter = progress
        self.suites = suites or {}
        self.done: dict[str, Manifest] = {}
        self._plan: StagePlan | None = None
        self.outcome = PhotoOutcome(photo, key)
        self.hash_photo: Callable[[Path], str] = file_sha256
        # Config hashes and prior resolution are the same for every photo with the same plan
        # decisions; a catalog-wide status check shares this between photos.
        self.memo: dict[Any, Any] = {}

    # -- what the stages see (``StageContext``) -----------------------------------------------

    @property
    def seed(self) -> int:
        return self.cfg.seed

    @property
    def device(self) -> str:
        return self.cfg.device

    @property
    def priors(self) -> PriorsConfig:
        return self.cfg.priors

    def dir(self, stage: str) -> Path:
        return self.store.stage_dir(self.key, stage)

    @property
    def stages(self) -> tuple[str, ...]:
        """The stages this photo goes through (``--init-mesh`` replaces the NeRF stage)."""
        return tuple(s.id for s in STAGES if not (s.replaced_by_init_mesh and self.init_mesh is not None))

    @property
    def plan(self) -> StagePlan | None:
        """The photo's plan, read once (after the stage that makes it is done)."""
        if self._plan is None:
            self._plan = read_plan(self.dir(PLANNER))
        return self._plan

    def upstream(self, stage: str) -> Manifest:
        """The finished output of ``stage``: from this run, else from the store."""
        if stage not in self.done:
            manifest = self.store.read_manifest(self.key, stage)
            if manifest is None:
                raise MissingUpstreamError(
                    f"{self.key}: stage {stage!r} has no finished output in {self.dir(stage)}; "
                    f"run it first (morpheus3d run … --until {stage}, or materialise its Dagster asset)")
            self.done[stage] = manifest
        return self.done[stage]

    def photo_hash(self) -> str:
        return self.hash_photo(self.photo)

    def prior_kind(self, roles: tuple[str, ...]) -> str:
        if self.suites:
            return "injected"
        key = ("prior_kind", id(self.cfg.priors), roles)
        if key not in self.memo:
            self.memo[key] = self.cfg.priors.resolve(roles)
        return self.memo[key]

    def suite(self, stage: str) -> PriorSuite | None:
        factory = self.suites.get(stage)
        return factory() if factory is not None else None

    def stage_checks(self, stage: str, thresholds: CheckThresholds) -> list[QACheck]:
        return stage_checks(stage, self.upstream(stage).metrics, thresholds)

    def progress(self) -> ProgressFn | None:
        if self.reporter is None:
            return None
        key, report = self.key, self.reporter
        return lambda e: report(ProgressEvent(f"{key}:{e.stage}", e.step, e.total, e.elapsed_s, e.metrics))

    # -- running a stage ----------------------------------------------------------------------

    def planned(self, stage: str) -> PlannedStage:
        """The stage's work for this photo and its fingerprint (raises ``MissingUpstreamError``
        when a stage it reads has no finished output)."""
        if stage not in self.stages:
            raise ValueError(f"{self.key}: stage {stage!r} is not part of this run (stages: {self.stages})")
        declared = BY_ID[stage]
        inputs = {s: output_digest(self.upstream(s)) for s in declared.reads if s in self.stages}
        work = declared.build(self, getattr(self.cfg, stage))
        key = ("config_hash", stage,
               tuple((k, id(v) if is_dataclass(v) else v) for k, v in sorted(work.config.items())))
        if key not in self.memo:
            record = stage_config_record(work.config)
            self.memo[key] = (config_hash(record), config_hash(whole_schedule_record(record)))
        full, whole = self.memo[key]
        inputs = {**inputs, **work.inputs}
        return PlannedStage(stage, work, Fingerprint(inputs, full, declared.code_version),
                            Fingerprint(inputs, whole, declared.code_version))

    def cached(self, planned: PlannedStage) -> Manifest | None:
        """The finished output matching the fingerprint, recorded as this run's output of the stage."""
        cached = self.store.lookup(self.key, planned.stage, planned.fingerprint, planned.whole_schedule)
        if cached is not None:
            self.outcome.stages.append(StageOutcome(planned.stage, "cached", 0.0, cached))
            self._report(planned.stage, "cached")
            self.done[planned.stage] = cached
        return cached

    def checkpoint_path(self, planned: PlannedStage) -> Path:
        return checkpoint_path(self.store, self.key, planned.stage, planned.whole_schedule)

    def adopt_layout1_checkpoint(self, planned: PlannedStage) -> bool:
        """Resume from the checkpoints a run from before store layout 2 left (they predate early
        stopping, so are of the whole schedule); False when there are none."""
        return adopt_layout1_checkpoint(self.store, self.key, planned.stage,
                                        whole_schedule_record(self.config_record(planned)), planned.whole_schedule)

    def config_record(self, planned: PlannedStage) -> dict[str, Any]:
        """The stage's config as plain JSON data: what the manifest records and the hash is of."""
        return stage_config_record(planned.work.config)

    def run(self, stage: str) -> Manifest:
        """Run ``stage`` (or reuse its cached output); raises when the stage fails."""
        planned = self.planned(stage)
        cached = self.cached(planned)
        return cached if cached is not None else self.execute(planned)

    def execute(self, planned: PlannedStage) -> Manifest:
        """Make the stage's output (no cache lookup), resuming from its checkpoint; raises on failure."""
        ckpt = self.checkpoint_path(planned)
        self.adopt_layout1_checkpoint(planned)
        resumed = ckpt.is_dir() and any(ckpt.iterdir())
        start = time.perf_counter()
        with self.store.stage_writer(self.key, planned.stage) as writer:
            result = planned.work.body(writer.path, ckpt)
            return self.commit(planned, writer, result, time.perf_counter() - start, resumed)

    def commit(self, planned: PlannedStage, writer: StageWriter, result: StageResult, wall: float,
               resumed: bool) -> Manifest:
        """Commit a finished stage folder with its manifest; its checkpoints are no longer needed."""
        stage = planned.stage
        plan = read_plan(writer.path) if stage == PLANNER else self.plan
        manifest = Manifest(
            stage=stage, photo_key=self.key, fingerprint=planned.recorded(result), outputs={},
            config=self.config_record(planned),
            metrics=result.metrics, wall_time_s=round(wall, 3), device=result.device, preset=self.preset,
            plan={} if plan is None else {"refine": plan.highpass_refinement.action,
                                          "grid": plan.dmtet_grid.value, "export_faces": plan.export.value,
                                          "summary": plan.summary()},
            prior=result.prior, notes=tuple(result.notes),
            created_at=datetime.now(timezone.utc).isoformat(timespec="seconds"),
        )
        manifest = writer.commit(manifest)
        self.store.clear_checkpoints(self.key, stage)
        status = "resumed" if resumed else "ran"
        if result.metrics.get("skipped"):
            status = "skipped"
        self.outcome.stages.append(StageOutcome(stage, status, wall, manifest))
        self._report(stage, status, wall)
        self.done[stage] = manifest
        return manifest

    def fail(self, stage: str, exc: Exception) -> None:
        """Record that ``stage`` failed for this photo (its later stages do not run)."""
        log.error("%s: stage %s failed: %s", self.key, stage, exc)
        # From the exception itself: a batch reports its photos' failures after leaving the handler.
        log.debug("%s", "".join(traceback.format_exception(exc)))
        self.outcome.exception = exc
        hint = memory_hint(exc)
        message = f"{exc} ({hint})" if hint else str(exc)
        self.outcome.error = f"{stage}: {type(exc).__name__}: {message}"
        self.outcome.stages.append(StageOutcome(stage, "failed", 0.0, None, message))

    def status(self) -> dict[str, str]:
        """Per stage: ``fresh`` (its output matches what this config and the current inputs would
        make), ``stale`` (an output exists but was made from something else) or ``missing``.
        Reads manifests only (no stage runs, no output re-hashing); downstream of a stale or
        missing stage is never fresh."""
        out: dict[str, str] = {}
        upstream_ok = True
        for stage in self.stages:
            manifest = self.store.read_manifest(self.key, stage)
            if manifest is None:
                out[stage], upstream_ok = "missing", False
                continue
            self.done[stage] = manifest  # downstream fingerprints read it as their input
            fresh = upstream_ok and self.planned(stage).matches(manifest.fingerprint)
            out[stage] = "fresh" if fresh else "stale"
            upstream_ok = upstream_ok and fresh
        return out

    def _report(self, stage: str, status: str, wall_s: float = 0.0) -> None:
        """The stage's outcome, with the seconds it took (0 for a cached one)."""
        if self.reporter is not None:
            self.reporter(ProgressEvent(f"{self.key}:{stage}:{status}", 1, 1, wall_s, {}))
