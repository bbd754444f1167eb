"""The Dagster code location loaded by ``workspace.yaml`` (``make dagster`` from the repo root).

Assets: ``photo_files`` (observable source: the watched folder) → ``reference`` → ``nerf`` → ``dmtet`` →
``texture`` → ``bake`` → ``export`` → ``qa`` (the stage ids of ``ops.stages``), one dynamic partition per
photo. The job ``morpheus_photos`` runs all seven for the photos it is given (sensor, nightly schedule,
backfills). Configuration: ``orchestration.settings`` (environment variables).
"""

from __future__ import annotations

import warnings

import dagster as dg

from ops.stages import STAGE_IDS
from orchestration.assets import build_assets
from orchestration.resources import MorpheusResource
from orchestration.schedules import build_nightly_schedule
from orchestration.sensors import build_folder_sensor
from orchestration.settings import OrchestrationSettings

JOB = "morpheus_photos"


def build_definitions(executor: dg.ExecutorDefinition | None = None,
                      settings: OrchestrationSettings | None = None) -> dg.Definitions:
    """The whole code location. ``executor`` defaults to ``settings.executor``: in-process (one
    photo's stages run in order anyway, and the priors' model cache then lives across stages) or
    multiprocess (each step in its own process; models are re-loaded from disk per step)."""
    settings = settings or OrchestrationSettings.from_env()
    job = dg.define_asset_job(JOB, selection=dg.AssetSelection.assets(*STAGE_IDS),
                              description="All seven stages for the photos (partitions) it is given.")
    resource = MorpheusResource(photo_dir=settings.photo_dir, store_root=settings.store_root, preset=settings.preset,
                                overrides=list(settings.overrides), settle_seconds=settings.settle_seconds)
    with warnings.catch_warnings():
        # We rely on three features Dagster marks beta/preview (observable partitioned source assets,
        # backfill policies, partitioned asset checks); dagster is pinned to 1.13.x in pyproject.toml
        # and the tests cover each, so the per-definition warnings would only be noise in every log.
        warnings.simplefilter("ignore", dg.BetaWarning)
        warnings.simplefilter("ignore", dg.PreviewWarning)
        assets = build_assets(settings)
    return dg.Definitions(
        assets=assets,
        jobs=[job],
        sensors=[build_folder_sensor(settings, job)],
        schedules=[build_nightly_schedule(settings, job)],
        resources={"morpheus": resource},
        executor=executor or (dg.in_process_executor if settings.executor == "in_process"
                              else dg.multiprocess_executor),
    )


defs = build_definitions()
