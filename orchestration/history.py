"""Dagster history across the stage-id renaming: the asset keys stages had before every stage got one
id, and carrying their materialisations over to the current keys.

Dagster keys history by asset key, so after the renaming the UI would show every photo of an
existing catalog as never materialised under the new keys (the store still holds the outputs, and
the schedule and sensor, which read the store, are not affected). ``migrate_history`` records, once
per photo and stage, a materialisation of the current key for each partition the old key had
materialised and whose output the store still holds, with that output's metadata, data version and
the old key it came from. The old keys' events stay in the event log as they were.
"""

from __future__ import annotations

import dagster as dg
from dagster._core.definitions.data_version import DATA_VERSION_TAG

from assets_store.store import Store
from ops.migrations import RENAMED_ASSETS
from ops.pipeline.photo_run import StageOutcome, output_digest
from orchestration.metadata import stage_metadata


def migrate_history(instance: dg.DagsterInstance, store: Store) -> dict[str, int]:
    """Per current asset key: how many partitions' materialisations were carried over now."""
    carried: dict[str, int] = {}
    for old, new in RENAMED_ASSETS.items():
        have = instance.get_materialized_partitions(dg.AssetKey(new))
        count = 0
        for partition in sorted(instance.get_materialized_partitions(dg.AssetKey(old)) - have):
            manifest = store.read_manifest(partition, new)
            if manifest is None:  # the output is gone (or was never migrated): nothing to show
                continue
            metadata = stage_metadata(StageOutcome(new, "migrated", 0.0, manifest), store.stage_dir(partition, new))
            metadata["migrated_from"] = old
            instance.report_runless_asset_event(dg.AssetMaterialization(
                asset_key=new, partition=partition, metadata=metadata,
                tags={DATA_VERSION_TAG: output_digest(manifest)}))
            count += 1
        carried[new] = count
    return carried
