"""One photo through every stage, with the store's caching, manifests and checkpoints.

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
import shutil
import time
import traceback
from collections.abc import Callable, Iterable, Sequence
from contextlib import AbstractContextManager, ExitStack, nullcontext
from dataclasses import dataclass, field, is_dataclass, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from assets_store.hashing import bytes_sha256, config_hash, file_sha256
from assets_store.manifest import Fingerprint, Manifest
from assets_store.photo_hashes import PhotoHashes
from assets_store.store import StageWriter, Store
from ops.config.presets import PipelineConfig
from ops.config.tree import to_dict
from ops.engine.batch import StageJob, run_jobs
from ops.engine.gpu_lease import GpuLease, leased_device
from ops.engine.loop import ProgressEvent, ProgressFn
from ops.engine.priors import WEIGHT_FREE, PriorSuite
from ops.engine.stage_io import StageResult, save_mask_overlay
from ops.stages import bake as uv_bake
from ops.stages import dmtet as dmtet_stage
from ops.stages import nerf as nerf_fit
from ops.stages import qa
from ops.stages import texture as texture_refine
from ops.stages.plan import StagePlan, plan_reference, read_plan
from ops.stages.reference import prepare_reference

log = logging.getLogger("morpheus3d")

STAGES = ("reference", "nerf_fit", "dmtet", "texture_refine", "uv_bake", "qa")
REFERENCE_CODE_VERSION = "reference-3"  # 2: the mask-overlay preview; 3: edge cue, every part, confidence
CODE_VERSIONS = {"reference": REFERENCE_CODE_VERSION, "nerf_fit": nerf_fit.CODE_VERSION,
                 "dmtet": dmtet_stage.CODE_VERSION, "texture_refine": texture_refine.CODE_VERSION,
                 "uv_bake": uv_bake.CODE_VERSION, "qa": qa.CODE_VERSION}


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


def output_digest(manifest: Manifest) -> str:
    """One hash for a stage's whole output (every file's content hash)."""
    return bytes_sha256(repr(sorted((k, v.sha256) for k, v in manifest.outputs.items())).encode())


class MissingUpstreamError(RuntimeError):
    """A stage was asked to run before the stage it reads from has a finished output."""


@dataclass(frozen=True)
class StageSpec:
    """What decides a stage's output (its config and input digests) and the body that makes it.

    ``start`` (optimising stages that will optimise): sets the stage up as a ``StageJob`` writing
    into the given folder, so several photos can run it together (``run_batch``)."""

    config: dict[str, Any]
    inputs: dict[str, str]
    body: Callable[[Path, Path | None], StageResult]
    start: Callable[[Path], StageJob] | None = None


class PhotoRun:
    """The state of one photo's run: where things are, what upstream produced, how to report."""

    def __init__(self, photo: Path, key: str, store: Store, cfg: PipelineConfig, preset: str,
                 init_mesh: Path | None, progress: ProgressFn | None,
                 suites: dict[str, Callable[[], PriorSuite]] | None) -> None:
        self.photo, self.key, self.store, self.cfg, self.preset = photo, key, store, cfg, preset
        self.init_mesh = init_mesh
        self.progress = progress
        self.suites = suites or {}
        self.done: dict[str, Manifest] = {}
        self._plan: StagePlan | None = None
        self.outcome = PhotoOutcome(photo, key)
        # The exception that stopped this photo: batch callers classify it (bad input or transient)
        # the way a single-photo caller classifies what ``run`` raises.
        self.error: Exception | None = None
        self.hash_photo: Callable[[Path], str] = file_sha256
        # Config hashes and prior resolution are the same for every photo with the same plan
        # decisions; a catalog-wide status check shares this between photos.
        self.memo: dict[Any, Any] = {}

    def dir(self, stage: str) -> Path:
        return self.store.stage_dir(self.key, stage)

    @property
    def stages(self) -> tuple[str, ...]:
        """The stages this photo goes through (``--init-mesh`` replaces the NeRF stage)."""
        return tuple(s for s in STAGES if not (s == "nerf_fit" and self.init_mesh is not None))

    @property
    def plan(self) -> StagePlan | None:
        """The reference stage's plan, read once (after the reference stage is done)."""
        if self._plan is None:
            self._plan = read_plan(self.dir("reference"))
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

    def digest(self, stage: str) -> str:
        return output_digest(self.upstream(stage))

    def prior_kind(self, roles: tuple[str, ...]) -> str:
        if self.suites:
            return "injected"
        key = ("prior_kind", id(self.cfg.priors), roles)
        if key not in self.memo:
            self.memo[key] = self.cfg.priors.resolve(roles)
        return self.memo[key]

    def fingerprint(self, stage: str, spec: StageSpec | None = None) -> Fingerprint:
        spec = spec or self.spec(stage)
        key = ("config_hash", stage,
               tuple((k, id(v) if is_dataclass(v) else v) for k, v in sorted(spec.config.items())))
        if key not in self.memo:
            self.memo[key] = config_hash(json.loads(json.dumps(to_dict(spec.config), default=str)))
        return Fingerprint(inputs=spec.inputs, config_hash=self.memo[key], code_version=CODE_VERSIONS[stage])

    def cached(self, stage: str, fp: Fingerprint) -> Manifest | None:
        """The finished output matching ``fp``, recorded as this run's output of ``stage``."""
        cached = self.store.lookup(self.key, stage, fp)
        if cached is not None:
            self.outcome.stages.append(StageOutcome(stage, "cached", 0.0, cached))
            self._report(stage, "cached")
            self.done[stage] = cached
        return cached

    def checkpoint_path(self, stage: str, spec: StageSpec, fp: Fingerprint) -> Path:
        root = self.store.checkpoint_dir(self.key, stage)
        return root / fp.config_hash[:12] / bytes_sha256(repr(sorted(spec.inputs.items())).encode())[:12]

    def run(self, stage: str) -> Manifest:
        """Run ``stage`` (or reuse its cached output); raises when the stage fails."""
        spec = self.spec(stage)
        fp = self.fingerprint(stage, spec)
        cached = self.cached(stage, fp)
        return cached if cached is not None else self.execute(stage, spec, fp)

    def execute(self, stage: str, spec: StageSpec, fp: Fingerprint) -> Manifest:
        """Make ``stage``'s output (no cache lookup), resuming from its checkpoint; raises on failure."""
        ckpt = self.checkpoint_path(stage, spec, fp)
        resumed = ckpt.is_dir() and any(ckpt.iterdir())
        start = time.perf_counter()
        with self.store.stage_writer(self.key, stage) as writer:
            result = spec.body(writer.path, ckpt)
            return self.commit(stage, spec, fp, writer, result, time.perf_counter() - start, resumed)

    def commit(self, stage: str, spec: StageSpec, fp: Fingerprint, writer: StageWriter, result: StageResult,
               wall: float, resumed: bool) -> Manifest:
        """Commit a finished stage folder with its manifest; its checkpoints are no longer needed."""
        plan = self.plan if stage != "reference" else read_plan(writer.path)
        manifest = Manifest(
            stage=stage, photo_key=self.key, fingerprint=fp, outputs={},
            config=json.loads(json.dumps(to_dict(spec.config), default=str)),
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
        self._report(stage, status)
        self.done[stage] = manifest
        return manifest

    def fail(self, stage: str, exc: Exception) -> None:
        """Record that ``stage`` failed for this photo (its later stages do not run)."""
        log.error("%s: stage %s failed: %s", self.key, stage, exc)
        # From the exception itself: a batch reports its photos' failures after leaving the handler.
        log.debug("%s", "".join(traceback.format_exception(exc)))
        self.error = exc
        self.outcome.error = f"{stage}: {type(exc).__name__}: {exc}"
        self.outcome.stages.append(StageOutcome(stage, "failed", 0.0, None, str(exc)))

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
            fresh = upstream_ok and manifest.fingerprint == self.fingerprint(stage)
            out[stage] = "fresh" if fresh else "stale"
            upstream_ok = upstream_ok and fresh
        return out

    def _report(self, stage: str, status: str) -> None:
        if self.progress is not None:
            self.progress(ProgressEvent(f"{self.key}:{stage}:{status}", 1, 1, 0.0, {}))

    def _progress(self) -> ProgressFn | None:
        if self.progress is None:
            return None
        key, report = self.key, self.progress
        return lambda e: report(ProgressEvent(f"{key}:{e.stage}", e.step, e.total, e.elapsed_s, e.metrics))

    def _suite(self, stage: str) -> PriorSuite | None:
        factory = self.suites.get(stage)
        return factory() if factory is not None else None

    # -- the stages ---------------------------------------------------------------------------

    def spec(self, stage: str) -> StageSpec:
        specs = {"reference": self._reference, "nerf_fit": self._nerf, "dmtet": self._dmtet,
                 "texture_refine": self._texture, "uv_bake": self._bake, "qa": self._qa}
        if stage not in self.stages:
            raise ValueError(f"{self.key}: stage {stage!r} is not part of this run (stages: {self.stages})")
        return specs[stage]()

    def _reference(self) -> StageSpec:
        cfg = self.cfg

        def body(out: Path, _ckpt: Path | None) -> StageResult:
            info = prepare_reference(self.photo, out, cfg.prepare)
            plan = plan_reference(out, cfg.plan)
            save_mask_overlay(out, out)
            return StageResult({"method": info.method, "area_fraction": round(info.area_fraction, 4),
                                "parts": info.kept_parts, "mask_confidence": info.confidence["score"],
                                "warnings": len(info.warnings), "plan": plan.summary()},
                               "none (segmentation)", "cpu", list(info.warnings))

        return StageSpec({"prepare": cfg.prepare, "plan": cfg.plan}, {"photo": self.hash_photo(self.photo)}, body)

    def _nerf(self) -> StageSpec:
        cfg = self.cfg
        config = {"nerf": cfg.nerf, "priors": cfg.priors, "prior_kind": self.prior_kind(cfg.nerf.guidance.roles),
                  "seed": cfg.seed}

        def start(out: Path) -> StageJob:
            return nerf_fit.start_nerf(self.dir("reference"), out, cfg.nerf, cfg.priors, self.key, cfg.device,
                                       cfg.seed, self._suite("nerf_fit"))

        return StageSpec(config, {"reference": self.digest("reference")},
                         lambda out, ckpt: start(out).run(ckpt, self._progress()), start)

    def _dmtet(self) -> StageSpec:
        cfg = self.cfg
        inputs = {"reference": self.digest("reference")}
        plan = self.plan
        grid = plan.dmtet_grid.value if plan is not None else None
        config = {"dmtet": cfg.dmtet, "priors": cfg.priors, "prior_kind": self.prior_kind(cfg.dmtet.guidance.roles),
                  "seed": cfg.seed, "planned_grid": grid}
        if self.init_mesh is not None:
            inputs["init_mesh"] = file_sha256(self.init_mesh)
        else:
            inputs["nerf_fit"] = self.digest("nerf_fit")

        def start(out: Path) -> StageJob:
            nerf_dir = None if self.init_mesh is not None else self.dir("nerf_fit")
            return dmtet_stage.start_dmtet(self.dir("reference"), out, cfg.dmtet, cfg.priors, self.key, nerf_dir,
                                           self.init_mesh, grid, cfg.device, cfg.seed, self._suite("dmtet"))

        return StageSpec(config, inputs, lambda out, ckpt: start(out).run(ckpt, self._progress()), start)

    def _texture(self) -> StageSpec:
        cfg = self.cfg
        inputs = {"reference": self.digest("reference"), "dmtet": self.digest("dmtet")}
        plan = self.plan
        refine = plan is None or plan.highpass_refinement.action != "skip"
        reason = "" if plan is None else plan.highpass_refinement.reason
        config = {"texture": cfg.texture, "priors": cfg.priors, "seed": cfg.seed, "planned_refine": refine,
                  "prior_kind": self.prior_kind(cfg.texture.guidance.roles)}

        if cfg.texture.follow_plan and not refine:
            return StageSpec(config, inputs, lambda out, _ckpt: texture_refine.pass_through(
                self.dir("dmtet"), out, cfg.device, reason))

        def start(out: Path) -> StageJob:
            return texture_refine.start_texture(self.dir("reference"), self.dir("dmtet"), out, cfg.texture,
                                                cfg.priors, self.key, cfg.device, cfg.seed,
                                                self._suite("texture_refine"))

        return StageSpec(config, inputs, lambda out, ckpt: start(out).run(ckpt, self._progress()), start)

    def _bake(self) -> StageSpec:
        cfg = self.cfg
        inputs = {k: self.digest(k) for k in ("reference", "dmtet", "texture_refine")}
        plan = self.plan
        faces = plan.export.value if plan is not None else None

        def body(out: Path, _ckpt: Path | None) -> StageResult:
            return uv_bake.bake_asset(self.dir("reference"), self.dir("dmtet"), self.dir("texture_refine"), out,
                                      cfg.bake, faces, cfg.device)

        return StageSpec({"bake": cfg.bake, "planned_faces": faces}, inputs, body)

    def _qa(self) -> StageSpec:
        cfg = self.cfg
        producers = [s for s in self.stages if s != "qa"]
        # Every producer is an input, the NeRF included (parts_kept renders it), so a changed
        # NeRF re-runs QA; with --init-mesh there is no NeRF stage and parts_kept is not measured.
        inputs = {s: self.digest(s) for s in producers}
        nerf_dir = self.dir("nerf_fit") if "nerf_fit" in producers else None

        def body(out: Path, _ckpt: Path | None) -> StageResult:
            upstream = {s: self.upstream(s).metrics for s in producers}
            prior = self.upstream("texture_refine").prior
            return qa.run_qa(self.dir("reference"), self.dir("uv_bake") / uv_bake.ASSET_GLB, out, cfg.qa, upstream,
                             prior, cfg.device, nerf_dir)

        return StageSpec({"qa": cfg.qa}, inputs, body)


def run_photo(photo: Path, store: Store, cfg: PipelineConfig, preset: str, key: str,
              init_mesh: Path | None = None, progress: ProgressFn | None = None,
              suites: dict[str, Callable[[], PriorSuite]] | None = None, until: str = "qa") -> PhotoOutcome:
    """Every stage for one photo, up to and including ``until``; never raises for a failing photo
    (the outcome says why)."""
    if until not in STAGES:
        raise ValueError(f"until must be one of {STAGES}, got {until!r}")
    store.cleanup_staging(key)
    with leased_device(cfg.device) as (device, lease):
        run = PhotoRun(Path(photo), key, store, replace(cfg, device=device), preset, init_mesh, progress, suites)
        for stage in [s for s in run.stages if STAGES.index(s) <= STAGES.index(until)]:
            try:
                run.run(stage)
            except Exception as exc:
                run.fail(stage, exc)
                break
    _record_lease(run.outcome.stages, lease)
    return run.outcome


def _record_lease(outcomes: Iterable[StageOutcome], lease: GpuLease | None) -> None:
    for outcome in outcomes:
        outcome.lease = None if lease is None else lease.describe()


def _stage_device(cfg: PipelineConfig, stage: str) -> AbstractContextManager[tuple[str, GpuLease | None]]:
    """The lease a single stage runs under: none for the CPU-only reference stage."""
    return nullcontext((cfg.device, None)) if stage == "reference" else leased_device(cfg.device)


def _batch_checkpoint(runs: list[tuple[PhotoRun, StageSpec, Fingerprint]], stage: str) -> Path:
    """One folder per batch composition (same photos, configs and inputs), under the first photo's
    checkpoints: re-running the same batch resumes it, another batch starts afresh."""
    first = runs[0][0]
    digest = bytes_sha256(repr(sorted(str(r.checkpoint_path(stage, spec, fp)) for r, spec, fp in runs)).encode())
    return first.store.checkpoint_dir(first.key, stage) / f"batch-{digest[:16]}"


def _run_stage_together(runs: list[PhotoRun], stage: str) -> None:
    """``stage`` for every run that has not failed: cached ones are reused, the optimising ones run
    as one batch (``ops.engine.batch``), the rest one by one. Failures are recorded per photo."""
    pending: list[tuple[PhotoRun, StageSpec, Fingerprint]] = []
    for run in runs:
        try:
            spec = run.spec(stage)
            fp = run.fingerprint(stage, spec)
            if run.cached(stage, fp) is not None:
                continue
            if spec.start is None:
                run.execute(stage, spec, fp)
            else:
                pending.append((run, spec, fp))
        except Exception as exc:
            run.fail(stage, exc)
    if len(pending) == 1:
        run, spec, fp = pending[0]
        try:
            run.execute(stage, spec, fp)
        except Exception as exc:
            run.fail(stage, exc)
        return
    if not pending:
        return
    ckpt = _batch_checkpoint(pending, stage)
    resumed = ckpt.is_dir() and any(ckpt.iterdir())
    start = time.perf_counter()
    with ExitStack() as stack:
        started: list[tuple[PhotoRun, StageSpec, Fingerprint, StageWriter, StageJob]] = []
        for run, spec, fp in pending:
            try:
                writer = stack.enter_context(run.store.stage_writer(run.key, stage))
                started.append((run, spec, fp, writer, spec.start(writer.path)))  # type: ignore[misc]
            except Exception as exc:
                run.fail(stage, exc)
        if not started:
            return
        keys = [r.key for r, *_ in started]
        progress = started[0][0].progress
        report = None if progress is None else (lambda e: progress(ProgressEvent(
            f"batch of {len(keys)}:{e.stage}", e.step, e.total, e.elapsed_s, e.metrics)))
        log.info("%s: %d photos optimised together (%s)", stage, len(keys), ", ".join(keys))
        try:
            results = run_jobs([job for *_, job in started], ckpt, report, started[0][0].cfg.seed)
        except Exception as exc:
            for run, *_ in started:
                run.fail(stage, exc)
            return
        wall = time.perf_counter() - start
        for (run, spec, fp, writer, _job), result in zip(started, results, strict=True):
            if isinstance(result, Exception):
                run.fail(stage, result)
                continue
            try:
                run.commit(stage, spec, fp, writer, result, wall, resumed)
            except Exception as exc:
                run.fail(stage, exc)
    shutil.rmtree(ckpt, ignore_errors=True)


def run_batch(photos: Sequence[tuple[Path, str]], store: Store, cfg: PipelineConfig, preset: str,
              init_mesh: Path | None = None, progress: ProgressFn | None = None,
              suites: dict[str, Callable[[], PriorSuite]] | None = None, until: str = "qa") -> list[PhotoOutcome]:
    """Every stage for several photos (``(photo, key)`` pairs), stage by stage: the optimising
    stages of all photos that need them run together as one batch, so one prior forward serves
    every photo. Same outputs, caching and manifests as ``run_photo``; a failing photo stops
    only itself. Each manifest's wall time is its batch's."""
    if until not in STAGES:
        raise ValueError(f"until must be one of {STAGES}, got {until!r}")
    for _, key in photos:
        store.cleanup_staging(key)
    with leased_device(cfg.device) as (device, lease):
        leased = replace(cfg, device=device)
        runs = [PhotoRun(Path(photo), key, store, leased, preset, init_mesh, progress, suites) for photo, key in photos]
        for stage in [s for s in STAGES if STAGES.index(s) <= STAGES.index(until)]:
            live = [r for r in runs if r.outcome.error is None and stage in r.stages]
            _run_stage_together(live, stage)
    for run in runs:
        _record_lease(run.outcome.stages, lease)
    return [r.outcome for r in runs]


def run_stage_batch(photos: Sequence[tuple[Path, str]], store: Store, cfg: PipelineConfig, preset: str,
                    stage: str, progress: ProgressFn | None = None) -> dict[str, StageOutcome | Exception]:
    """One stage for several photos (``(photo, key)`` pairs) reading their inputs from the store;
    those that must optimise run together as one batch (what a Dagster step over several photos
    calls). Per key: the stage's outcome, or the exception that ``run_stage`` would have raised for
    that photo alone. A batch is resumed from its checkpoints only when re-run with the same photos."""
    if stage not in STAGES:
        raise ValueError(f"stage must be one of {STAGES}, got {stage!r}")
    with _stage_device(cfg, stage) as (device, lease):
        runs = [PhotoRun(Path(photo), key, store, replace(cfg, device=device), preset, None, progress, None)
                for photo, key in photos]
        _run_stage_together(runs, stage)
    for run in runs:
        _record_lease(run.outcome.stages[-1:], lease)
    return {r.key: r.error if r.error is not None else r.outcome.stages[-1] for r in runs}


def run_stage(photo: Path, store: Store, cfg: PipelineConfig, preset: str, key: str, stage: str,
              init_mesh: Path | None = None, progress: ProgressFn | None = None,
              suites: dict[str, Callable[[], PriorSuite]] | None = None) -> StageOutcome:
    """One stage for one photo, reading its inputs from the store (what a Dagster asset calls).

    Cached when its fingerprint matches, resumed from its newest checkpoint when one exists.
    Raises on failure (``MissingUpstreamError`` when an input stage has no finished output), so
    an orchestrator can retry; finished outputs and checkpoints stay in place."""
    with _stage_device(cfg, stage) as (device, lease):
        run = PhotoRun(Path(photo), key, store, replace(cfg, device=device), preset, init_mesh, progress, suites)
        run.run(stage)
    _record_lease(run.outcome.stages[-1:], lease)
    return run.outcome.stages[-1]


def photo_status(photo: Path, store: Store, cfg: PipelineConfig, key: str, init_mesh: Path | None = None,
                 hashes: PhotoHashes | None = None, memo: dict[Any, Any] | None = None) -> dict[str, str]:
    """Per stage: ``fresh`` / ``stale`` / ``missing`` (see ``PhotoRun.status``). For a whole catalog,
    ``hashes`` avoids re-reading unchanged photos and one shared ``memo`` (with the same ``cfg``
    object) avoids re-hashing the same configuration for every photo."""
    run = PhotoRun(Path(photo), key, store, cfg, "", init_mesh, None, None)
    if hashes is not None:
        run.hash_photo = hashes.sha256
    if memo is not None:
        run.memo = memo
    return run.status()


def uses_weight_free(outcome: PhotoOutcome) -> bool:
    return any(s.manifest is not None and s.manifest.prior.startswith(WEIGHT_FREE) for s in outcome.stages)
