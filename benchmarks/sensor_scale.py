"""How the folder sensor and the nightly catch-up scale with the catalog (Dagster's sensor limit is 60 s).

Sensor: a folder of N photo files (tiny PNGs) and a SQLite Dagster instance, timed for one tick in
three states: cold start (no partition known yet: the tick adds ``cap`` photos), steady state
(all but ``cap`` known) and idle (all known). Nightly catch-up: the per-photo status check
(``ops.engine.pipeline.photo_status``: photo hash from the hash cache + every stage's manifest) timed on
a finished store and extrapolated to N photos.

    python benchmarks/sensor_scale.py --files 100000 --store outputs/demo --photos examples/photos
"""

from __future__ import annotations

import argparse
import io
import json
import os
import platform
import shutil
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

import dagster as dg
import numpy as np
from PIL import Image

from assets_store.keys import assign_keys
from assets_store.photo_hashes import PhotoHashes
from assets_store.store import Store
from ops.config.presets import preset
from ops.engine.pipeline import photo_status
from orchestration.definitions import build_definitions
from orchestration.partitions import PHOTOS
from orchestration.settings import OrchestrationSettings

RESULTS = Path(__file__).parent / "results"


def _png() -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.random.default_rng(0).integers(0, 255, (8, 8, 3), dtype=np.uint8)).save(buf, format="PNG")
    return buf.getvalue()


def _tick(defs: dg.Definitions, instance: dg.DagsterInstance) -> tuple[float, dg.SensorResult]:
    sensor = defs.resolve_sensor_def("photo_folder_sensor")
    context = dg.build_sensor_context(instance=instance, resources={"morpheus": defs.resources["morpheus"]})
    start = time.perf_counter()
    result = sensor(context)
    return time.perf_counter() - start, result


def bench_sensor(n: int, cap: int, root: Path) -> dict:
    folder = root / "photos"
    folder.mkdir()
    data = _png()
    old = time.time() - 3600
    start = time.perf_counter()
    for i in range(n):
        path = folder / f"product_{i:06d}.png"
        path.write_bytes(data)
        os.utime(path, (old, old))
    (folder / "readme.txt").write_text("not a photo")
    write_s = time.perf_counter() - start
    settings = OrchestrationSettings(photo_dir=str(folder), store_root=str(root / "store"),
                                     sensor_max_new_per_tick=cap, settle_seconds=30.0)
    defs = build_definitions(settings=settings)
    home = root / "home"
    home.mkdir()
    out = {"files": n, "cap_per_tick": cap, "write_files_s": round(write_s, 1)}
    with dg.instance_for_test(temp_dir=str(home)) as instance:
        cold_s, cold = _tick(defs, instance)
        out["cold_start_tick_s"] = round(cold_s, 3)
        out["cold_start_added"] = len(cold.run_requests)
        keys = sorted(assign_keys(p.name for p in folder.iterdir() if p.suffix == ".png").values())
        start = time.perf_counter()
        instance.add_dynamic_partitions(PHOTOS, keys[: n - cap])
        out["register_partitions_s"] = round(time.perf_counter() - start, 2)
        steady_s, steady = _tick(defs, instance)
        out["steady_tick_s"] = round(steady_s, 3)
        out["steady_added"] = len(steady.run_requests)
        instance.add_dynamic_partitions(PHOTOS, keys[n - cap:])
        idle_s, idle = _tick(defs, instance)
        out["idle_tick_s"] = round(idle_s, 3)
        out["idle_added"] = len(idle.run_requests or [])
        start = time.perf_counter()
        instance.get_dynamic_partitions(PHOTOS)
        out["read_known_keys_s"] = round(time.perf_counter() - start, 3)
    return out


def bench_status(store_root: Path, photos: Path, preset_name: str, n: int, repeats: int) -> dict:
    store, cfg = Store(store_root), preset(preset_name)
    names = {k: photos / v for v, k in assign_keys(p.name for p in photos.iterdir() if p.is_file()).items()}
    keys = [k for k in store.keys() if k in names]
    hashes, memo = PhotoHashes(store_root), {}
    statuses = {k: photo_status(names[k], store, cfg, k, hashes=hashes, memo=memo) for k in keys}  # warm caches
    start = time.perf_counter()
    for _ in range(repeats):
        for k in keys:
            photo_status(names[k], store, cfg, k, hashes=hashes, memo=memo)
    per_photo = (time.perf_counter() - start) / (repeats * max(1, len(keys)))
    return {"photos_checked": len(keys), "statuses": statuses, "status_ms_per_photo": round(per_photo * 1e3, 2),
            "extrapolated_s_for_catalog": round(per_photo * n, 1), "catalog": n}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--files", type=int, default=100_000)
    parser.add_argument("--cap", type=int, default=100)
    parser.add_argument("--store", type=Path, default=Path("outputs/demo"), help="a finished store (make demo)")
    parser.add_argument("--photos", type=Path, default=Path("examples/photos"))
    parser.add_argument("--preset", default="draft")
    parser.add_argument("--name", default="sensor_scale_cpu")
    args = parser.parse_args()
    root = Path(tempfile.mkdtemp(prefix="sensor_scale_"))
    try:
        sensor = bench_sensor(args.files, args.cap, root)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    status = bench_status(args.store, args.photos, args.preset, args.files, repeats=20) if args.store.is_dir() else {}
    result = {"date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "machine": platform.node(),
              "cpu_count": os.cpu_count(), "python": platform.python_version(), "dagster": dg.__version__,
              "sensor": sensor, "nightly_status": status}
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{args.name}.json").write_text(json.dumps(result, indent=2))
    s = sensor
    lines = [f"# Folder sensor and nightly catch-up at scale ({result['date']}, {result['cpu_count']} CPU cores, "
             f"Dagster {dg.__version__}, SQLite instance)", "",
             f"A folder of {s['files']:,} photo files; at most {s['cap_per_tick']} photos added per tick. "
             "Dagster times a sensor out after 60 s.", "",
             "| sensor tick | time | photos added |", "|---|---|---|",
             f"| cold start (no partition known) | {s['cold_start_tick_s']:.2f} s | {s['cold_start_added']} |",
             f"| steady state ({s['files'] - s['cap_per_tick']:,} known, {s['cap_per_tick']} new) | "
             f"{s['steady_tick_s']:.2f} s | {s['steady_added']} |",
             f"| idle (all known) | {s['idle_tick_s']:.2f} s | {s['idle_added']} |", "",
             f"Reading the {s['files']:,} known partition keys: {s['read_known_keys_s']:.2f} s. Registering "
             f"{s['files'] - s['cap_per_tick']:,} partitions in one call: {s['register_partitions_s']:.1f} s.", ""]
    if status:
        lines += ["## Nightly catch-up", "",
                  f"Status check of a finished photo (hash cache + six manifests): "
                  f"{status['status_ms_per_photo']:.2f} ms per photo, measured on {status['photos_checked']} "
                  f"photos × 20; extrapolated to {status['catalog']:,} photos: "
                  f"{status['extrapolated_s_for_catalog']:.0f} s (an extrapolation, not a run over that many)."]
    (RESULTS / f"{args.name}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
