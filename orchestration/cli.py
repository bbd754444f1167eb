"""``morpheus3d-dagster``: register photos as partitions and materialise them through Dagster.

    morpheus3d-dagster add-photos [NAME ...]        register photos of $MORPHEUS_PHOTO_DIR, print keys
    morpheus3d-dagster materialize [NAME ...]       run all seven assets per photo, in this process
    morpheus3d-dagster status                       fresh / stale / missing per photo
    morpheus3d-dagster gpu-pool [--limit N]         set the "gpu" pool's limit to GPUs × MORPHEUS_GPU_SLOTS
    morpheus3d-dagster migrate-history              carry materialisations of renamed asset keys over

Runs are recorded in the instance at ``$DAGSTER_HOME`` (``make dagster`` shows them in the UI).
Backfills through the daemon: ``dagster job backfill -w workspace.yaml -j morpheus_photos
--partitions KEY,KEY --noprompt`` (see the README).
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TextIO

import dagster as dg

from ops.config.preset_names import PRESET_NAMES
from ops.engine.checks import read_report
from ops.engine.gpu_lease import GPUS_ENV, SLOTS_ENV, gpu_count, gpu_slots
from ops.stages.bake import ASSET_GLB
from orchestration.assets import GPU_POOL
from orchestration.definitions import JOB, build_definitions
from orchestration.history import migrate_history
from orchestration.partitions import PHOTOS
from orchestration.resources import MorpheusResource
from orchestration.schedules import needs_run
from orchestration.settings import OrchestrationSettings

# Stage progress and failures (INFO and up), not Dagster's per-event DEBUG lines.
QUIET = {"loggers": {"console": {"config": {"log_level": "INFO"}}}}


def _select(resource: MorpheusResource, names: Sequence[str]) -> list[str]:
    """Photo keys for file names (or keys) in the watched folder; all photos when none are named."""
    photos = resource.photos()
    if not names:
        return sorted(photos)
    by_name = {v: k for k, v in photos.items()}
    keys, unknown = [], []
    for name in names:
        base = Path(name).name
        key = name if name in photos else by_name.get(base)
        (keys if key else unknown).append(key or name)
    if unknown:
        raise SystemExit(f"not in {resource.photo_dir}: {', '.join(unknown)} (photos there: "
                         f"{', '.join(sorted(photos.values())[:10])}{' …' if len(photos) > 10 else ''})")
    return keys


def _instance() -> dg.DagsterInstance:
    if not os.environ.get("DAGSTER_HOME"):
        raise SystemExit("DAGSTER_HOME is not set: point it at a folder holding dagster.yaml "
                         "(the project's is ./dagster_home; `make dagster` sets it)")
    Path(os.environ["DAGSTER_HOME"]).mkdir(parents=True, exist_ok=True)
    return dg.DagsterInstance.get()


def materialize(settings: OrchestrationSettings, names: Sequence[str]) -> int:
    defs = build_definitions(settings=settings)
    resource: MorpheusResource = defs.resources["morpheus"]
    keys = _select(resource, names)
    instance = _instance()
    instance.add_dynamic_partitions(PHOTOS, keys)
    gpu_pool(None, force=False, out=sys.stderr)
    job = defs.resolve_job_def(JOB)
    rows, failed = [], 0
    for i, key in enumerate(keys, 1):
        print(f"[{i}/{len(keys)}] {key}: materialising seven assets …", file=sys.stderr, flush=True)
        start = time.perf_counter()
        result = job.execute_in_process(partition_key=key, instance=instance, raise_on_error=False,
                                        tags={"morpheus/trigger": "cli"}, run_config=QUIET)
        wall = time.perf_counter() - start
        store = resource.store()
        glb = store.stage_dir(key, "bake") / ASSET_GLB
        if result.success:
            report = read_report(store.stage_dir(key, "qa"))
            psnr = report.metrics.get("ref_psnr")
            rows.append((key, "ok", f"{wall:.0f}", report.verdict, f"{psnr:.1f}" if psnr else "-", str(glb),
                         "; ".join(report.reasons) or "-"))
        else:
            failed += 1
            step = next((e for e in result.all_events if e.event_type_value == "STEP_FAILURE"), None)
            why = step.event_specific_data.error.message.strip().splitlines()[-1] if step else "run failed"
            rows.append((key, "FAILED", f"{wall:.0f}", "-", "-", "-", why[:200]))
    header = ("photo", "run", "time s", "QA", "ref PSNR dB", "GLB", "QA reasons / failure")
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header) - 1)]
    for row in [header, *rows]:
        print("  ".join(str(c).ljust(w) for c, w in zip(row, widths, strict=False)) + "  " + str(row[-1]))
    print(f"\nQA reports: {settings.store_root}/<photo>/qa/qa.json · 3D viewers at real size: "
          f"{settings.store_root}/<photo>/qa/viewer.html · true-size GLB, web GLB, USDZ: "
          f"{settings.store_root}/<photo>/export/ · runs and previews: `make dagster`, then http://127.0.0.1:3000/runs")
    return 1 if failed else 0


def gpu_pool(limit: int | None, force: bool, out: TextIO | None = None) -> int:
    """Set the ``gpu`` pool's limit to the leases runs may hold here, GPUs × ``MORPHEUS_GPU_SLOTS``
    (``ops.engine.gpu_lease``; at least 1, so a CPU host still runs its GPU stages on the CPU one at
    a time). A limit set before is kept unless ``force``.

    ``add-photos`` and ``materialize`` call it too: a pool left on dagster.yaml's ``default_limit``
    is created by the first GPU step that claims a slot, and on Postgres two runs doing that at once
    fail one of them (duplicate key in ``concurrency_limits``; Dagster issue 33552). A limit set
    here is never re-initialised by the steps. ``out``: where to say what it did (None: the
    ``sys.stdout`` of the moment, not of import time, so a redirected or captured stdout hears it)."""
    out = out or sys.stdout
    storage = _instance().event_log_storage
    found, slots = gpu_count(), gpu_slots()
    wanted = limit if limit is not None else max(1, found * slots)
    if GPU_POOL in storage.get_concurrency_keys() and not force:
        current = storage.get_concurrency_info(GPU_POOL).slot_count
        print(f"pool {GPU_POOL!r} keeps its limit {current} ({found} GPU(s) × {slots} slot(s) found; --force sets "
              f"{wanted})", file=out)
        return 0
    try:
        storage.set_concurrency_slots(GPU_POOL, wanted)
    except Exception:  # another process set it at the same moment: keep theirs
        if GPU_POOL not in storage.get_concurrency_keys():
            raise
        print(f"pool {GPU_POOL!r} was just set by another process", file=out)
        return 0
    print(f"pool {GPU_POOL!r} limit {wanted} ({found} GPU(s) found via {GPUS_ENV} / CUDA_VISIBLE_DEVICES / torch, "
          f"{slots} run(s) each: {SLOTS_ENV})", file=out)
    return 0


# Help text is plain (no reStructuredText ``literals`` or Markdown `code`): people read it in a terminal.
DESCRIPTION = "Register photos as partitions and materialise them through Dagster."
EPILOG = ("Runs are recorded in the Dagster instance at $DAGSTER_HOME (make dagster shows them in the UI). "
          "Backfills through the daemon: dagster job backfill -w workspace.yaml -j morpheus_photos "
          "--partitions KEY,KEY --noprompt (see the README).")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="morpheus3d-dagster", description=DESCRIPTION, epilog=EPILOG)
    parser.add_argument("--photos", type=Path, help="photo folder (default $MORPHEUS_PHOTO_DIR or examples/photos)")
    parser.add_argument("--store", type=Path, help="asset store root (default $MORPHEUS_STORE)")
    parser.add_argument("--preset", choices=PRESET_NAMES, help="default $MORPHEUS_PRESET or draft")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, text in (("add-photos", "register photos as partitions and print their keys"),
                       ("materialize", "run all seven assets for the photos, one run per photo, in this process"),
                       ("status", "fresh / stale / missing stages per registered photo")):
        p = sub.add_parser(name, help=text)
        if name != "status":
            p.add_argument("names", nargs="*", help="photo file names in the folder (default: all)")
    pool = sub.add_parser("gpu-pool", help="set the gpu pool's limit to the GPUs found × MORPHEUS_GPU_SLOTS")
    pool.add_argument("--limit", type=int, help="this limit instead of the GPU count")
    pool.add_argument("--force", action="store_true", help="replace a limit set before")
    sub.add_parser("migrate-history", help="show the materialisations of the asset keys from before the stage ids "
                                           "were unified under the current keys (once; make dagster runs it)")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "gpu-pool":
        return gpu_pool(args.limit, args.force)
    env = dict(os.environ)
    for flag, var in ((args.photos, "MORPHEUS_PHOTO_DIR"), (args.store, "MORPHEUS_STORE"),
                      (args.preset, "MORPHEUS_PRESET")):
        if flag is not None:
            env[var] = str(flag)
    settings = OrchestrationSettings.from_env(env)
    logging.basicConfig(level=logging.WARNING)
    resource = build_definitions(settings=settings).resources["morpheus"]
    if args.command == "add-photos":
        keys = _select(resource, args.names)
        _instance().add_dynamic_partitions(PHOTOS, keys)
        gpu_pool(None, force=False, out=sys.stderr)  # before any run claims a slot (see gpu_pool)
        print(",".join(keys))
        return 0
    if args.command == "migrate-history":
        carried = migrate_history(_instance(), resource.store())
        print("carried over: " + ", ".join(f"{k} {n}" for k, n in carried.items()))
        return 0
    if args.command == "status":
        keys = _instance().get_dynamic_partitions(PHOTOS)
        for key, status in sorted(resource.status(keys).items()):
            print(f"{key}: {needs_run(status) or 'up to date'}  ({', '.join(f'{s} {v}' for s, v in status.items())})")
        return 0
    return materialize(settings, args.names)


if __name__ == "__main__":
    raise SystemExit(main())
