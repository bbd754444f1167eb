"""The photo source asset and one asset per declared stage: thin wrappers over ``ops.pipeline.runner.Pipeline``.

Each stage asset runs its stage (``Pipeline.run(photos, [stage])``) for every photo partition of its step, then
reports the store's manifest as metadata and the stage's QA checks (declared on its ``Stage``, gathered in
``ops.stages.CHECKS``) as asset check results. A step covering several photos (a backfill batch) keeps going
past a failing photo, records what finished, then fails naming the photos that did not, so a retry redoes only
those (finished ones are cached; interrupted ones resume from their checkpoints). In such a step
the GPU stages optimise their photos together (one ``Pipeline.run`` for the step's photos: one prior
forward per step for all of them) unless ``MORPHEUS_BATCH_TOGETHER=0``.
"""


import time
from collections.abc import Callable, Iterator
from typing import Any

import dagster as dg
from dagster import AssetExecutionContext

from assets_store.keys import UnsafeKeyError
from assets_store.photo_hashes import PhotoHashes
from morpheus_core.priors.proxy.shape import EmptySilhouetteError
from ops.engine.checks import ERROR, QACheck, read_report
from ops.engine.config_tree import ConfigError
from ops.engine.progress import HEARTBEAT_S, ProgressEvent
from ops.engine.stage import Stage
from ops.intake.errors import PreparationError
from ops.pipeline.photo_run import MissingUpstreamError, StageOutcome, output_digest
from ops.reporting.progress import format_event
from ops.stages import BY_ID, CHECKS, STAGE_IDS, STAGES, stage_checks
from orchestration.metadata import check_metadata, stage_metadata
from orchestration.partitions import PHOTOS, photos
from orchestration.resources import MorpheusResource, UnknownPhotoError
from orchestration.settings import OrchestrationSettings

GROUP = "morpheus3d"
GPU_POOL = "gpu"
# GPU requests for the Kubernetes executor (ignored by the local executors).
GPU_TAGS = {"dagster-k8s/config": {"container_config": {"resources": {"limits": {"nvidia.com/gpu": "1"}}}}}
# Bad input or configuration: retrying cannot help, so these fail at once with their message.
PERMANENT = (PreparationError, ConfigError, MissingUpstreamError, UnknownPhotoError, UnsafeKeyError,
             EmptySilhouetteError)


# What a stage with no upstream stage reads: the photo source asset.
PHOTO_SOURCE = "photo_files"
# A photo's catalog row is appended once its last stage is done.
LAST_STAGE = STAGE_IDS[-1]


def _severity(check: QACheck) -> dg.AssetCheckSeverity:
    return dg.AssetCheckSeverity.ERROR if check.severity == ERROR else dg.AssetCheckSeverity.WARN


def _checks(outcome: StageOutcome, morpheus: MorpheusResource, key: str) -> list[QACheck]:
    if BY_ID[outcome.stage].judge is None:  # a stage that judges its own output writes a QA report
        report = read_report(morpheus.store().stage_dir(key, outcome.stage))
        return [QACheck(**c) for c in report.checks[outcome.stage]]
    assert outcome.manifest is not None
    return stage_checks(outcome.stage, outcome.manifest.metrics, morpheus.pipeline_config().qa)


def _logging_progress(context: AssetExecutionContext, every_s: float = HEARTBEAT_S) -> Callable[[ProgressEvent], None]:
    """Step progress in the run log, at most every ``every_s`` seconds (and at the end); a phase
    without steps (the NeRF → DMTet conversion, QA's renders) at each of its heartbeats."""
    last = [0.0]

    def report(event: ProgressEvent) -> None:
        if event.total <= 0:  # a heartbeat of a long call: its phase may contain ':' itself
            context.log.info(format_event(event))
            return
        if event.stage.count(":") == 2:  # "key:stage:status" once a stage is done
            context.log.info(f"{event.stage.replace(':', ' · ')} ({event.elapsed_s:.0f} s)")
            return
        now = time.monotonic()
        if event.step >= event.total or now - last[0] >= every_s:
            last[0] = now
            shown = ", ".join(f"{k} {v:.4g}" for k, v in event.metrics.items() if isinstance(v, (int, float)))
            context.log.info(f"{event.stage}: step {event.step}/{event.total} ({event.elapsed_s:.0f} s) {shown}")

    return report


def _failure(context: AssetExecutionContext, morpheus: MorpheusResource, stage: str, key: str, exc: Exception,
             max_retries: int) -> Exception:
    """What a photo's failed stage raises. Bad input cannot be fixed by retrying: it is recorded in
    the catalog at once and becomes a non-retryable ``dg.Failure``; anything else may be transient,
    so it stays as it is and reaches the catalog only on the last attempt."""
    reason = f"{stage}: {type(exc).__name__}: {exc}"
    if isinstance(exc, PERMANENT):
        morpheus.record(key, context.run.run_id, {stage: "failed"}, reason)
        return dg.Failure(description=f"{key}: {type(exc).__name__}: {exc}", allow_retries=False)
    if context.retry_number >= max_retries:
        morpheus.record(key, context.run.run_id, {stage: "failed"}, reason)
    return exc


def _run_one(context: AssetExecutionContext, morpheus: MorpheusResource, stage: str, key: str,
             max_retries: int) -> StageOutcome:
    try:
        return morpheus.run_stage(key, stage, _logging_progress(context))
    except Exception as exc:
        failure = _failure(context, morpheus, stage, key, exc, max_retries)
        if failure is exc:
            raise
        raise failure from exc


def _make_stage_asset(spec: Stage, settings: OrchestrationSettings) -> dg.AssetsDefinition:
    check_specs = [dg.AssetCheckSpec(c.name, asset=spec.id, description=c.description, partitions_def=photos)
                   for c in CHECKS[spec.id]]

    @dg.asset(
        name=spec.id, description=spec.description, group_name=GROUP, partitions_def=photos,
        deps=list(spec.reads or (PHOTO_SOURCE,)), code_version=spec.code_version, check_specs=check_specs,
        pool=GPU_POOL if spec.gpu else None, op_tags=GPU_TAGS if spec.gpu else None,
        kinds={"pytorch"} if spec.gpu else {"python"},
        retry_policy=dg.RetryPolicy(max_retries=settings.max_retries, delay=settings.retry_delay_s,
                                    backoff=dg.Backoff.EXPONENTIAL, jitter=dg.Jitter.PLUS_MINUS),
        backfill_policy=dg.BackfillPolicy.multi_run(settings.backfill_batch),
    )
    def stage_asset(context: AssetExecutionContext, morpheus: MorpheusResource) -> Iterator[Any]:
        keys = list(context.partition_keys)
        if len(keys) == 1:
            outcome = _run_one(context, morpheus, spec.id, keys[0], settings.max_retries)
            if spec.id == LAST_STAGE:
                morpheus.record(keys[0], context.run.run_id, {spec.id: outcome.status})
            checks = _checks(outcome, morpheus, keys[0])
            assert outcome.manifest is not None
            yield dg.MaterializeResult(
                metadata=stage_metadata(outcome, morpheus.store().stage_dir(keys[0], spec.id)),
                data_version=dg.DataVersion(output_digest(outcome.manifest)),
                check_results=[dg.AssetCheckResult(check_name=c.name, passed=c.passed, severity=_severity(c),
                                                   description=c.message, metadata=check_metadata(c))
                               for c in checks])
            return
        yield from _batch(context, morpheus, spec, keys, settings.max_retries, spec.gpu and settings.batch_together)

    return stage_asset


def _stage_outcomes(context: AssetExecutionContext, morpheus: MorpheusResource, stage: str, keys: list[str],
                    together: bool) -> Iterator[tuple[str, StageOutcome | Exception]]:
    """Per photo of the step: its stage outcome, or the exception that stopped it."""
    if together:
        context.log.info(f"{len(keys)} photos optimised together: {stage} ({', '.join(keys)})")
        results: dict[str, StageOutcome | Exception]
        try:
            results = morpheus.run_stage_batch(keys, stage, _logging_progress(context))
        except Exception as exc:  # what the photos share failed (configuration, store): all of them
            results = dict.fromkeys(keys, exc)
        yield from results.items()
        return
    for i, key in enumerate(keys, 1):
        context.log.info(f"[{i}/{len(keys)}] {key}: {stage}")
        try:
            yield key, morpheus.run_stage(key, stage, _logging_progress(context))
        except Exception as exc:
            yield key, exc


def _batch(context: AssetExecutionContext, morpheus: MorpheusResource, spec: Stage,
           keys: list[str], max_retries: int, together: bool) -> Iterator[Any]:
    """A step over several photos (run ``together`` as one batch, or one after another): one
    photo's failure does not stop the others."""
    done: dict[str, tuple[StageOutcome, list[QACheck]]] = {}
    failed: dict[str, str] = {}
    retry = False  # whether any failure might pass on a retry (bad input never does)
    for key, outcome in _stage_outcomes(context, morpheus, spec.id, keys, together):
        try:
            if isinstance(outcome, Exception):
                raise _failure(context, morpheus, spec.id, key, outcome, max_retries)
            done[key] = (outcome, _checks(outcome, morpheus, key))
            if spec.id == LAST_STAGE:
                morpheus.record(key, context.run.run_id, {spec.id: outcome.status})
        except Exception as exc:  # recorded per photo; the step fails below
            failed[key] = f"{type(exc).__name__}: {exc}"
            retry = retry or not (isinstance(exc, dg.Failure) and not exc.allow_retries)
            context.log.error(f"{key}: {spec.id} failed: {failed[key]}")
    asset_key = dg.AssetKey(spec.id)
    for key, (_, checks) in done.items():
        for c in checks:
            yield dg.AssetCheckEvaluation(
                asset_key=asset_key, check_name=c.name, passed=c.passed, severity=_severity(c),
                description=c.message, metadata=check_metadata(c), partition=key)
    if failed:
        # The step fails, so Dagster records no materialisation for its range: record the finished photos.
        for key, (outcome, _) in done.items():
            yield dg.AssetMaterialization(
                asset_key=asset_key, partition=key,
                metadata=stage_metadata(outcome, morpheus.store().stage_dir(key, spec.id)))
        raise dg.Failure(description=f"{spec.id}: {len(failed)} of {len(keys)} photos failed: "
                         + "; ".join(f"{k}: {v}" for k, v in failed.items()),
                         metadata={"failed": dg.MetadataValue.json(failed)}, allow_retries=retry)
    table = ["| photo | status | wall s | ref PSNR | verdict / checks |", "|---|---|---|---|---|"]
    for key, (outcome, checks) in done.items():
        m = outcome.manifest
        assert m is not None
        psnr = m.metrics.get("ref_psnr")
        bad = [c.name for c in checks if not c.passed]
        table.append(f"| {key} | {outcome.status} | {m.wall_time_s:.1f} | "
                     f"{'' if psnr is None else f'{psnr:.1f}'} | {', '.join(bad) or 'all passed'} |")
    summaries = []
    for c in CHECKS[spec.id]:
        failing = [k for k, (_, cs) in done.items() if any(x.name == c.name and not x.passed for x in cs)]
        summaries.append(dg.AssetCheckResult(
            check_name=c.name, passed=not failing,
            severity=dg.AssetCheckSeverity.ERROR if c.severity == ERROR else dg.AssetCheckSeverity.WARN,
            description=f"batch of {len(keys)}: " + (f"failed for {', '.join(failing)}" if failing else "all passed")))
    yield dg.MaterializeResult(metadata={"photos": len(keys), "batch": dg.MetadataValue.md("\n".join(table))},
                               check_results=summaries)


def build_photo_source(settings: OrchestrationSettings) -> dg.SourceAsset:
    @dg.observable_source_asset(
        name=PHOTO_SOURCE, group_name=GROUP, partitions_def=photos, required_resource_keys={"morpheus"},
        description="The product photos in the watched folder; data version = content hash (sha256), so a "
                    "changed photo makes exactly its own partition's stages stale.")
    def photo_files(context: AssetExecutionContext) -> dg.DataVersionsByPartition:
        morpheus: MorpheusResource = context.resources.morpheus
        names = morpheus.photos()
        hashes = PhotoHashes(morpheus.store_root)
        versions = {k: hashes.sha256(morpheus.photo_path(k, names)) for k in
                    context.instance.get_dynamic_partitions(PHOTOS) if k in names}
        hashes.save()
        return dg.DataVersionsByPartition(versions)

    return photo_files


def build_assets(settings: OrchestrationSettings) -> list[Any]:
    return [build_photo_source(settings), *(_make_stage_asset(s, settings) for s in STAGES)]

