"""The nightly catch-up: runs only for photos whose stages are missing or stale, never the catalog.

A photo is stale when what its stages were made from differs from now (the photo's content, the
configuration, the code version — the store's fingerprints, ``ops.pipeline.photo_run.PhotoRun.status``) and
missing when a stage has no output. ``build_schedule_from_partitioned_job`` rejects dynamic
partitions, so this is a plain ``@schedule`` returning one run request per such photo.
"""


import dagster as dg
from dagster._core.definitions.unresolved_asset_job_definition import UnresolvedAssetJobDefinition

from orchestration.partitions import PHOTOS
from orchestration.resources import MorpheusResource
from orchestration.settings import OrchestrationSettings


def needs_run(status: dict[str, str]) -> str | None:
    """``missing`` / ``stale`` when a photo needs a run, else None."""
    values = set(status.values())
    if "stale" in values:
        return "stale"
    if "missing" in values:
        return "missing"
    return None


def build_nightly_schedule(settings: OrchestrationSettings,
                           job: UnresolvedAssetJobDefinition) -> dg.ScheduleDefinition:
    @dg.schedule(name="nightly_catch_up", job=job, cron_schedule=settings.nightly_cron,
                 execution_timezone=settings.timezone, default_status=dg.DefaultScheduleStatus.STOPPED,
                 description="Every night: a run for each photo whose stages are missing or stale.")
    def nightly_catch_up(context: dg.ScheduleEvaluationContext,
                         morpheus: MorpheusResource) -> dg.SkipReason | list[dg.RunRequest]:
        keys = context.instance.get_dynamic_partitions(PHOTOS)
        statuses = morpheus.status(keys)
        stamp = context.scheduled_execution_time.strftime("%Y-%m-%d") if context.scheduled_execution_time else "now"
        requests = []
        for key, status in sorted(statuses.items()):
            reason = needs_run(status)
            if reason is not None:
                requests.append(dg.RunRequest(partition_key=key, run_key=f"nightly:{stamp}:{key}",
                                              tags={"morpheus/trigger": "nightly", "morpheus/reason": reason}))
        if not requests:
            return dg.SkipReason(f"all {len(statuses)} photos are up to date")
        context.log.info(f"{len(requests)} of {len(statuses)} photos need a run")
        return requests

    return nightly_catch_up
