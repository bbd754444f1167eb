"""The pipeline: photos through the declared stages (``ops.stages``), stage by stage.

One entry point, ``Pipeline.run(photos, stages=…)``, behind the command line (a photo, or a group
of ``--batch`` photos, through every stage up to ``--until``), Dagster (one stage of one or several
photos per step) and the benchmarks. For each stage, every photo that needs it is planned
(``ops.pipeline.photo_run``): cached outputs are reused, and the photos that must optimise run as
one batch (``ops.engine.batch``), so one prior forward serves every photo; a stage that does not
optimise runs photo by photo. Same outputs, caching and manifests whatever the grouping; a failing
photo stops only itself.
"""

from __future__ import annotations

import logging
import shutil
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import ExitStack, contextmanager, nullcontext
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from assets_store.hashing import bytes_sha256
from assets_store.photo_hashes import PhotoHashes
from assets_store.store import StageWriter, Store
from morpheus_core.runtime.execution import executing
from ops.config.presets import PipelineConfig
from ops.engine.batch import run_jobs
from ops.engine.gpu_lease import GpuLease, leased_device
from ops.engine.priors import WEIGHT_FREE, PriorSuite
from ops.engine.progress import ProgressEvent, ProgressFn
from ops.engine.stage_job import StageJob
from ops.pipeline.photo_run import PhotoOutcome, PhotoRun, PlannedStage
from ops.stages import BY_ID, STAGE_IDS

log = logging.getLogger("morpheus3d")


def check_stage_id(stage: str, what: str = "stage") -> str:
    if stage not in STAGE_IDS:
        raise ValueError(f"{what} must be one of {STAGE_IDS}, got {stage!r}")
    return stage


def stages_until(until: str) -> tuple[str, ...]:
    """The stages up to and including ``until``, in pipeline order (``morpheus3d run --until``)."""
    return STAGE_IDS[:STAGE_IDS.index(check_stage_id(until, "until")) + 1]


@dataclass
class Pipeline:
    """The stages assembled for one store and configuration.

    ``preset`` is the name the manifests record; ``init_mesh`` replaces the stages declared
    ``replaced_by_init_mesh``; ``suites`` injects prior suites by stage (the benchmarks' oracles)."""

    store: Store
    cfg: PipelineConfig
    preset: str = ""
    init_mesh: Path | None = None
    progress: ProgressFn | None = None
    suites: dict[str, Callable[[], PriorSuite]] | None = None

    def run(self, photos: Sequence[tuple[Path, str]], stages: Iterable[str] | None = None) -> list[PhotoOutcome]:
        """``stages`` (default: all; run in pipeline order) for every ``(photo, key)``, stage by stage.

        A stage a photo needs but not listed is read from the store (``MissingUpstreamError`` when it
        has no finished output). Never raises for a failing photo: its outcome says why
        (``PhotoOutcome.error``, ``.exception``) and its later stages do not run. A batch of photos
        resumes from its checkpoints only when re-run with the same photos."""
        selected = set(STAGE_IDS if stages is None else (check_stage_id(s) for s in stages))
        order = [s for s in STAGE_IDS if s in selected]
        for _, key in photos:
            self.store.cleanup_staging(key)
        with run_setup(self.cfg, needs_device=not all(BY_ID[s].cpu_only for s in order)) as (cfg, lease):
            runs = [PhotoRun(Path(photo), key, self.store, cfg, self.preset, self.init_mesh, self.progress,
                             self.suites) for photo, key in photos]
            for stage in order:
                run_stage_together([r for r in runs if r.outcome.error is None and stage in r.stages], stage)
        for run in runs:
            for outcome in run.outcome.stages:
                outcome.lease = None if lease is None else lease.describe()
        return [r.outcome for r in runs]

    def status(self, photo: Path, key: str, hashes: PhotoHashes | None = None,
               memo: dict[Any, Any] | None = None) -> dict[str, str]:
        """Per stage: ``fresh`` / ``stale`` / ``missing`` (``PhotoRun.status``). For a whole catalog,
        ``hashes`` avoids re-reading unchanged photos and one shared ``memo`` (with this pipeline's
        ``cfg``) avoids re-hashing the same configuration for every photo."""
        run = PhotoRun(Path(photo), key, self.store, self.cfg, self.preset, self.init_mesh, None, None)
        if hashes is not None:
            run.hash_photo = hashes.sha256
        if memo is not None:
            run.memo = memo
        return run.status()


def uses_weight_free(outcome: PhotoOutcome) -> bool:
    return any(s.manifest is not None and s.manifest.prior.startswith(WEIGHT_FREE) for s in outcome.stages)


@contextmanager
def run_setup(cfg: PipelineConfig, needs_device: bool = True) -> Iterator[tuple[PipelineConfig, GpuLease | None]]:
    """Where every run starts: ``cfg.execution`` applied process-wide for the run (the kernels read it,
    ``morpheus_core.runtime.execution``; the previous settings come back after it), and the device leased
    (``ops.engine.gpu_lease``) unless no stage of the run touches it. Yields ``cfg`` on the leased
    device, and the lease."""
    lease_cm = leased_device(cfg.device) if needs_device else nullcontext((cfg.device, None))
    with executing(cfg.execution), lease_cm as (device, lease):
        yield replace(cfg, device=device), lease


def _batch_checkpoint(runs: list[tuple[PhotoRun, PlannedStage]], stage: str) -> Path:
    """One folder per batch composition (same photos, configs and inputs), under the first photo's
    checkpoints: re-running the same batch resumes it, another batch starts afresh."""
    first = runs[0][0]
    digest = bytes_sha256(repr(sorted(str(r.checkpoint_path(p)) for r, p in runs)).encode())
    return first.store.checkpoint_dir(first.key, stage) / f"batch-{digest[:16]}"


def run_stage_together(runs: list[PhotoRun], stage: str) -> None:
    """``stage`` for every run: cached ones are reused, the optimising ones run as one batch
    (``ops.engine.batch``; alone when only one photo optimises), the rest one by one. Failures are
    recorded per photo."""
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
