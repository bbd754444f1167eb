"""The folder sensor: new, completely uploaded photos become partitions and get a run each.

Per tick: the known partition keys are read once (per-key lookups cost ~2 ms each), the folder is
listed by name only, and only new names are looked at closely (age, end-of-file marker), at most
``4 × cap`` of them, so a 100k-file folder costs one directory listing. At most ``cap`` photos are
added per tick; the rest wait for the next tick. The cursor records the photos still waiting for
their upload to settle, so the tick's message can say what it is waiting for.
"""


import json
import time
from pathlib import Path

import dagster as dg
from dagster._core.definitions.unresolved_asset_job_definition import UnresolvedAssetJobDefinition

from ops.intake.photo_folder import upload_state
from orchestration.partitions import PHOTOS, photos
from orchestration.resources import MorpheusResource
from orchestration.settings import OrchestrationSettings


def build_folder_sensor(settings: OrchestrationSettings, job: UnresolvedAssetJobDefinition) -> dg.SensorDefinition:
    cap = settings.sensor_max_new_per_tick

    @dg.sensor(name="photo_folder_sensor", job=job, minimum_interval_seconds=settings.sensor_interval_s,
               default_status=dg.DefaultSensorStatus.STOPPED,
               description=f"Adds new photos from the watched folder as partitions and runs them "
                           f"(at most {cap} per tick; partial uploads wait until complete).")
    def photo_folder_sensor(context: dg.SensorEvaluationContext, morpheus: MorpheusResource) -> dg.SensorResult:
        start = time.perf_counter()
        known = set(context.instance.get_dynamic_partitions(PHOTOS))
        names = morpheus.photos()
        new = sorted(k for k in names if k not in known)
        now = time.time()
        ready: list[str] = []
        waiting: dict[str, str] = {}
        for key in new[: 4 * cap]:
            state = upload_state(Path(morpheus.photo_dir) / names[key], morpheus.settle_seconds, now)
            if state.ready:
                ready.append(key)
                if len(ready) == cap:
                    break
            else:
                waiting[key] = state.reason
        backlog = len(new) - len(ready) - len(waiting)
        cursor = {"waiting": sorted(waiting)[:100], "backlog": backlog, "known": len(known) + len(ready),
                  "tick_s": round(time.perf_counter() - start, 3)}
        if not ready:
            example = next(iter(waiting.items()), ("", ""))
            reason = "no new photos" if not new else (
                f"{len(waiting)} new file(s) still uploading, e.g. {example[0]}: {example[1]}")
            return dg.SensorResult(skip_reason=reason, cursor=json.dumps(cursor))
        context.log.info(f"adding {len(ready)} photos ({len(waiting)} still uploading, {backlog} for later ticks)")
        return dg.SensorResult(
            run_requests=[dg.RunRequest(partition_key=k, run_key=f"new:{k}", tags={"morpheus/trigger": "sensor"})
                          for k in ready],
            dynamic_partitions_requests=[photos.build_add_request(ready)],
            cursor=json.dumps(cursor))

    return photo_folder_sensor
