"""Several photos through the pipeline together: each optimising stage of all photos that need it
runs as one batch (``ops.engine.batch``), so one prior forward serves every photo; the rest is
``ops.engine.pipeline`` photo by photo (same outputs, caching and manifests)."""

from __future__ import annotations

import logging
import shutil
import time
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from pathlib import Path

from assets_store.hashing import bytes_sha256
from assets_store.store import StageWriter, Store
from ops.config.presets import PipelineConfig
from ops.engine.batch import run_jobs
from ops.engine.pipeline import (
    PhotoOutcome,
    PhotoRun,
    PlannedStage,
    StageOutcome,
    check_stage_id,
    record_lease,
    run_setup,
)
from ops.engine.priors import PriorSuite
from ops.engine.progress import ProgressEvent, ProgressFn
from ops.engine.stage_ids import STAGE_IDS
from ops.engine.stage_job import StageJob

log = logging.getLogger("morpheus3d")


def _batch_checkpoint(runs: list[tuple[PhotoRun, PlannedStage]], stage: str) -> Path:
    """One folder per batch composition (same photos, configs and inputs), under the first photo's
    checkpoints: re-running the same batch resumes it, another batch starts afresh."""
    first = runs[0][0]
    digest = bytes_sha256(repr(sorted(str(r.checkpoint_path(p)) for r, p in runs)).encode())
    return first.store.checkpoint_dir(first.key, stage) / f"batch-{digest[:16]}"


def _run_stage_together(runs: list[PhotoRun], stage: str) -> None:
    """``stage`` for every run that has not failed: cached ones are reused, the optimising ones run
    as one batch (``ops.engine.batch``), the rest one by one. Failures are recorded per photo."""
    pending: list[tuple[PhotoRun, PlannedStage]] = []
    for run in runs:
        try:
            planned = run.planned(stage)
            if run.cached(planned) is not None:
                continue
            if planned.work.start is None:
                run.execute(planned)
            else:
                pending.append((run, planned))
        except Exception as exc:
            run.fail(stage, exc)
    if len(pending) == 1:
        run, planned = pending[0]
        try:
            run.execute(planned)
        except Exception as exc:
            run.fail(stage, exc)
        return
    if not pending:
        return
    ckpt = _batch_checkpoint(pending, stage)
    resumed = ckpt.is_dir() and any(ckpt.iterdir())
    start = time.perf_counter()
    with ExitStack() as stack:
        started: list[tuple[PhotoRun, PlannedStage, StageWriter, StageJob]] = []
        for run, planned in pending:
            try:
                writer = stack.enter_context(run.store.stage_writer(run.key, stage))
                started.append((run, planned, writer, planned.work.start(writer.path)))  # type: ignore[misc]
            except Exception as exc:
                run.fail(stage, exc)
        if not started:
            return
        keys = [r.key for r, *_ in started]
        progress = started[0][0].reporter
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
        for (run, planned, writer, _job), result in zip(started, results, strict=True):
            if isinstance(result, Exception):
                run.fail(stage, result)
                continue
            try:
                run.commit(planned, writer, result, wall, resumed)
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
    last = STAGE_IDS.index(check_stage_id(until, "until"))
    for _, key in photos:
        store.cleanup_staging(key)
    with run_setup(cfg) as (leased, lease):
        runs = [PhotoRun(Path(photo), key, store, leased, preset, init_mesh, progress, suites) for photo, key in photos]
        for stage in STAGE_IDS[:last + 1]:
            live = [r for r in runs if r.outcome.error is None and stage in r.stages]
            _run_stage_together(live, stage)
    for run in runs:
        record_lease(run.outcome.stages, lease)
    return [r.outcome for r in runs]


def run_stage_batch(photos: Sequence[tuple[Path, str]], store: Store, cfg: PipelineConfig, preset: str,
                    stage: str, progress: ProgressFn | None = None) -> dict[str, StageOutcome | Exception]:
    """One stage for several photos (``(photo, key)`` pairs) reading their inputs from the store;
    those that must optimise run together as one batch (what a Dagster step over several photos
    calls). Per key: the stage's outcome, or the exception that ``run_stage`` would have raised for
    that photo alone. A batch is resumed from its checkpoints only when re-run with the same photos."""
    check_stage_id(stage)
    with run_setup(cfg, stage) as (leased, lease):
        runs = [PhotoRun(Path(photo), key, store, leased, preset, None, progress, None) for photo, key in photos]
        _run_stage_together(runs, stage)
    for run in runs:
        record_lease(run.outcome.stages[-1:], lease)
    return {r.key: r.error if r.error is not None else r.outcome.stages[-1] for r in runs}
