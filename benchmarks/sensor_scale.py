"""How the folder sensor and the nightly catch-up scale with the catalog, on a SQLite and a Postgres
Dagster instance (Dagster times a sensor or a schedule evaluation out after 60 s by default).

Setup: a folder of N photo files (hardlinks of one bundled photo, ``product_000000.jpg`` …) and a
store holding N finished photos, cloned from one finished photo of ``--store`` (``make demo``):
per key a copy of its stage folders with the output files hardlinked and each ``manifest.json``
rewritten for the new key (the only file naming the key that the status check reads). The clones
are up to date by the real check: same photo content, same configuration, same upstream outputs.

Per instance (``--instance sqlite|postgres|both``; Postgres: a throwaway server from
``tests.postgres_server``, the project's ``dagster_home*/dagster.yaml``):

* sensor: one tick of ``photo_folder_sensor`` in three states: cold start (no partition known yet:
  the tick adds ``cap`` photos), steady state (all but ``cap`` known) and idle (all known); also
  registering the partitions and reading the N known keys back;
* nightly catch-up, measured at N (not extrapolated): the real ``nightly_catch_up`` schedule
  evaluated end to end (``evaluate_tick``: partitions read from the instance, status of every
  photo, run requests) on the instance holding the N partitions: first night (empty photo-hash
  cache: every photo hashed) and next night (cache warm). It must find all N photos up to date;
  anything else stops the benchmark.

    python -m benchmarks.sensor_scale --files 10000 --instance both --name sensor_scale_10k
    python -m benchmarks.sensor_scale --files 100000 --instance sqlite --no-nightly   # sensor only
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path

import dagster as dg

from assets_store.hashing import bytes_sha256
from assets_store.keys import assign_keys
from assets_store.manifest import MANIFEST_FILE, Manifest
from assets_store.photo_hashes import CACHE_FILE
from assets_store.store import Store
from ops.config.presets import preset
from ops.engine.store_layout import LAYOUT_FILE, open_store
from ops.intake import photo_folder
from ops.pipeline.photo_run import output_digest
from ops.pipeline.runner import Pipeline
from ops.stages import STAGE_IDS
from orchestration.definitions import build_definitions
from orchestration.partitions import PHOTOS
from orchestration.settings import OrchestrationSettings

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).parent / "results"
TIMEOUT_S = 60.0  # DAGSTER_SENSOR_GRPC_TIMEOUT_SECONDS / DAGSTER_SCHEDULE_GRPC_TIMEOUT_SECONDS default
SMALL = 1 << 20  # files up to this size are searched for the source key


def _name(i: int, suffix: str) -> str:
    return f"product_{i:06d}{suffix}"


# -- the catalog: N photo files and N finished photos in the store -----------------------------------


def source_photo(store_root: Path, photos: Path, preset_name: str, wanted: str | None) -> tuple[str, Path]:
    """A finished photo of the store (key, photo file), checked up to date by the real status check."""
    names = {k: photos / v for v, k in assign_keys(p.name for p in photos.iterdir() if p.is_file()).items()}
    pipeline = Pipeline(open_store(store_root), preset(preset_name))
    for key in [wanted] if wanted else pipeline.store.keys():
        if key in names and set(pipeline.status(names[key], key).values()) == {"fresh"}:
            return key, names[key]
    raise SystemExit(f"{store_root} has no finished, up-to-date photo of {photos} for preset {preset_name!r}"
                     f"{f' (asked for {wanted})' if wanted else ''}: run `make demo` first")


def make_photo_folder(folder: Path, n: int, photo: Path) -> float:
    """N hardlinks of one copy of ``photo`` (an hour old, so the sensor sees it uploaded), and a non-photo."""
    start = time.perf_counter()
    folder.mkdir()
    original = folder.parent / f"source{photo.suffix}"
    shutil.copyfile(photo, original)
    old = time.time() - 3600
    os.utime(original, (old, old))
    for i in range(n):
        os.link(original, folder / _name(i, photo.suffix))
    (folder / "readme.txt").write_text("not a photo")
    return time.perf_counter() - start


def _dumps(data: dict) -> str:
    return json.dumps(data, indent=2, sort_keys=True, allow_nan=False) + "\n"  # Manifest.to_json's format


def clone_store(src_root: Path, src_key: str, src_photo: Path, dst_root: Path, photos: dict[str, Path]) -> dict:
    """Every key of ``photos`` (key → its photo file) as a copy of ``src_key``'s finished stages.

    Output files are hardlinked, except small text outputs naming the source photo's path (the
    reference stage's ``reference.json``): those are rewritten with the clone's path, as the
    pipeline would have written them, and the clone's manifests follow: ``photo_key``, the
    rewritten file's size and hash, and downstream stages' fingerprint inputs (the reference
    stage's output digest). Nothing else differs from the source photo's real output.
    """
    start = time.perf_counter()
    dst_root.mkdir()
    shutil.copyfile(src_root / LAYOUT_FILE, dst_root / LAYOUT_FILE)  # else open_store would migrate it
    src = src_root / src_key
    stages = [s for s in STAGE_IDS if (src / s / MANIFEST_FILE).is_file()]
    old_paths = sorted({str(src_photo.resolve()), str(src_photo.absolute())}, key=len, reverse=True)
    manifests: dict[str, dict] = {}
    links: list[Path] = []  # relative paths hardlinked unchanged
    rewrite: dict[str, dict[str, str]] = {}  # stage → {output name: its text}
    binary_mentions: list[str] = []
    for stage in stages:
        text = (src / stage / MANIFEST_FILE).read_text(encoding="utf-8")
        data = json.loads(text)
        if _dumps(data) != text or Manifest.from_json(text).photo_key != src_key:
            raise RuntimeError(f"{src_key}/{stage}/{MANIFEST_FILE}: not a manifest of {src_key} as written")
        manifests[stage] = data
        for name in data["outputs"]:
            path = src / stage / name
            raw = path.read_bytes() if path.stat().st_size <= SMALL else b""
            if any(o.encode() in raw for o in [*old_paths, src_key]):
                try:
                    rewrite.setdefault(stage, {})[name] = raw.decode("utf-8")
                    continue
                except UnicodeDecodeError:
                    binary_mentions.append(f"{stage}/{name}")
            links.append(Path(stage) / name)
    digests = {s: output_digest(Manifest.from_json(_dumps(m))) for s, m in manifests.items()}
    leftover: set[str] = set()
    n_links = n_written = 0
    for key, photo in photos.items():
        dst = dst_root / key
        dst.mkdir()
        for stage in stages:
            (dst / stage).mkdir()
        for rel in links:
            os.link(src / rel, dst / rel)
        n_links += len(links)
        new_path = json.dumps(str(photo.resolve()))[1:-1]
        new_digest: dict[str, str] = {}
        for stage in stages:
            data = {**manifests[stage], "photo_key": key}
            if stage in rewrite:
                outputs = dict(data["outputs"])
                for name, text in rewrite[stage].items():
                    for old in old_paths:
                        text = text.replace(json.dumps(old)[1:-1], new_path)
                    text = text.replace(json.dumps(src_key), json.dumps(key))
                    if src_key in text:
                        leftover.add(f"{stage}/{name}")
                    raw = text.encode("utf-8")
                    (dst / stage / name).write_bytes(raw)
                    outputs[name] = {"sha256": bytes_sha256(raw), "size": len(raw)}
                data["outputs"] = outputs
            inputs = data["fingerprint"]["inputs"]
            if any(s in inputs and inputs[s] == digests[s] for s in new_digest):
                data["fingerprint"] = {**data["fingerprint"],
                                       "inputs": {s: new_digest.get(s, v) if v == digests.get(s) else v
                                                  for s, v in inputs.items()}}
            text = _dumps(data)
            (dst / stage / MANIFEST_FILE).write_text(text, encoding="utf-8")
            n_written += 1
            if stage in rewrite:
                new_digest[stage] = output_digest(Manifest.from_json(text))
    store = Store(dst_root)
    sample = sorted(photos)[:: max(1, len(photos) // 3)]
    if not all(store.verify(k, s) for k in sample for s in stages):  # every byte against the manifests
        raise RuntimeError(f"a cloned stage of {sample} does not verify")
    return {"clone_s": round(time.perf_counter() - start, 1), "source_key": src_key, "stages": stages,
            "files_per_photo": len(links) + len(stages) + sum(map(len, rewrite.values())),
            "hardlinked_files": n_links, "manifests_written": n_written,
            "rewritten_outputs": sorted(f"{s}/{n}" for s, d in rewrite.items() for n in d),
            "binary_outputs_naming_the_source": binary_mentions, "rewritten_still_naming_source_key": sorted(leftover),
            "verified_photos": len(sample)}


# -- Dagster instances ------------------------------------------------------------------------------


@contextmanager
def _env(extra: dict[str, str]) -> Iterator[None]:
    saved = {k: os.environ.get(k) for k in extra}
    os.environ.update(extra)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _postgres_version() -> str:
    from tests.postgres_server import server_bin

    bindir = server_bin()
    if bindir is None:
        return "not installed"
    return subprocess.run([str(bindir / "postgres"), "--version"], capture_output=True, text=True).stdout.strip()


@contextmanager
def dagster_instance(kind: str, home: Path) -> Iterator[dg.DagsterInstance]:
    """The project's instance configuration (``dagster_home*/dagster.yaml``) in a fresh DAGSTER_HOME."""
    home.mkdir()
    if kind == "sqlite":
        shutil.copyfile(ROOT / "dagster_home" / "dagster.yaml", home / "dagster.yaml")
        with _env({"DAGSTER_HOME": str(home)}), dg.DagsterInstance.from_config(str(home)) as instance:
            yield instance
        return
    from tests.postgres_server import postgres_server

    shutil.copyfile(ROOT / "dagster_home_postgres" / "dagster.yaml", home / "dagster.yaml")
    with postgres_server() as pg, _env({**pg, "DAGSTER_HOME": str(home)}), \
            dg.DagsterInstance.from_config(str(home)) as instance:
        yield instance


# -- measurements -----------------------------------------------------------------------------------


def _tick(defs: dg.Definitions, instance: dg.DagsterInstance) -> tuple[float, dg.SensorResult]:
    sensor = defs.resolve_sensor_def("photo_folder_sensor")
    context = dg.build_sensor_context(instance=instance, resources={"morpheus": defs.resources["morpheus"]})
    start = time.perf_counter()
    result = sensor(context)
    return time.perf_counter() - start, result


def bench_sensor(defs: dg.Definitions, instance: dg.DagsterInstance, folder: Path, n: int, cap: int) -> dict:
    photo_folder._LAST_SCAN.clear()  # a fresh code server: no folder listing remembered yet
    out: dict = {}
    cold_s, cold = _tick(defs, instance)
    out["cold_start_tick_s"] = round(cold_s, 3)
    out["cold_start_added"] = len(cold.run_requests)
    keys = sorted(photo_folder.scan(folder))
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
    known = instance.get_dynamic_partitions(PHOTOS)
    out["read_known_keys_s"] = round(time.perf_counter() - start, 3)
    if len(known) != n or out["cold_start_added"] != min(cap, n) or out["idle_added"]:
        raise RuntimeError(f"sensor bench: {len(known)} partitions known of {n}, {out}")
    return out


def _night(defs: dg.Definitions, instance: dg.DagsterInstance, n: int, when: datetime) -> dict:
    schedule = defs.resolve_schedule_def("nightly_catch_up")
    context = dg.build_schedule_context(instance=instance, scheduled_execution_time=when,
                                        resources={"morpheus": defs.resources["morpheus"]})
    start = time.perf_counter()
    data = schedule.evaluate_tick(context)
    wall = time.perf_counter() - start
    requests = list(data.run_requests or [])
    match = re.fullmatch(r"all (\d+) photos are up to date", data.skip_message or "")
    up_to_date = int(match[1]) if match else n - len(requests)
    if requests or up_to_date != n:
        reasons = sorted({(r.partition_key, r.tags.get("morpheus/reason")) for r in requests})[:5]
        raise RuntimeError(f"nightly catch-up found {up_to_date} of {n} photos up to date, {len(requests)} run "
                           f"requests (e.g. {reasons}); skip message {data.skip_message!r}")
    return {"wall_s": round(wall, 2), "photos_up_to_date": up_to_date, "run_requests": len(requests),
            "ms_per_photo": round(wall / n * 1e3, 3), "under_60s": wall < TIMEOUT_S,
            "skip_message": data.skip_message}


def bench_nightly(defs: dg.Definitions, instance: dg.DagsterInstance, store_root: Path, n: int) -> dict:
    (store_root / CACHE_FILE).unlink(missing_ok=True)
    when = datetime(2026, 1, 1, 2, 0, tzinfo=timezone.utc)
    first = _night(defs, instance, n, when)  # every photo hashed (its cache entry is new)
    cache_kb = (store_root / CACHE_FILE).stat().st_size // 1024
    return {"first_night": first, "next_night": _night(defs, instance, n, when), "photo_hash_cache_kb": cache_kb}


def bench_instance(kind: str, root: Path, folder: Path, store_root: Path, n: int, cap: int, preset_name: str,
                   nightly: bool) -> dict:
    settings = OrchestrationSettings(photo_dir=str(folder), store_root=str(store_root), preset=preset_name,
                                     sensor_max_new_per_tick=cap, settle_seconds=30.0)
    defs = build_definitions(settings=settings)
    start = time.perf_counter()
    with dagster_instance(kind, root / f"home_{kind}") as instance:
        out = {"open_instance_s": round(time.perf_counter() - start, 2), "storage": type(instance.run_storage).__name__}
        print(f"[{kind}] sensor …", flush=True)
        out["sensor"] = bench_sensor(defs, instance, folder, n, cap)
        print(f"[{kind}] {out['sensor']}", flush=True)
        if nightly:
            print(f"[{kind}] nightly catch-up over {n:,} photos …", flush=True)
            out["nightly"] = bench_nightly(defs, instance, store_root, n)
            print(f"[{kind}] {out['nightly']}", flush=True)
    return out


# -- report -----------------------------------------------------------------------------------------


def _s(value: float) -> str:
    return f"{value:.2f} s" if value < 10 else f"{value:.1f} s"


def _ok(value: float) -> str:
    return "yes" if value < TIMEOUT_S else "**no**"


def markdown(result: dict) -> str:
    inst = result["instances"]
    kinds = list(inst)
    n, cap = result["files"], result["cap_per_tick"]
    head = "| | " + " | ".join(kinds) + " |"
    rule = "|---|" + "---|" * len(kinds)

    def row(label: str, cell) -> str:
        return f"| {label} | " + " | ".join(cell(inst[k]) for k in kinds) + " |"

    def tick(name: str):
        return lambda d: f"{_s(d['sensor'][name + '_tick_s'])} (under 60 s: {_ok(d['sensor'][name + '_tick_s'])})"

    lines = [f"# Folder sensor and nightly catch-up at {n:,} photos: {' vs '.join(kinds)}", "",
             f"{result['date']}, `{result['machine']}`, {result['cpu_count']} CPU cores ({result['cpu_model']}, "
             f"load average {result['load_average_at_start']} at start, "
             f"{result['load_average_at_end']} at the end: shared), Python {result['python']}, "
             f"Dagster {result['dagster']}, {result['postgres']}.", "",
             f"Command: `{result['command']}`", "",
             f"A folder of {n:,} photo files (hardlinks of one bundled photo)"
             + (f" and a store of {n:,} finished photos (clones of `{result['store']['source_key']}` from "
                f"`{result['store']['source_store']}`, preset {result['preset']})" if result["store"] else "")
             + f". At most {cap} photos added per sensor tick. Dagster times a sensor or a schedule evaluation "
             "out after 60 s by default (`DAGSTER_SENSOR_GRPC_TIMEOUT_SECONDS`, "
             "`DAGSTER_SCHEDULE_GRPC_TIMEOUT_SECONDS`).", "",
             "## Folder sensor", "", head, rule,
             row("cold start tick (no partition known)", tick("cold_start")),
             row(f"steady state tick ({n - cap:,} known, {cap} new)", tick("steady")),
             row("idle tick (all known)", tick("idle")),
             row(f"registering {n - cap:,} partitions (one call)", lambda d: _s(d["sensor"]["register_partitions_s"])),
             row(f"reading the {n:,} known keys", lambda d: f"{d['sensor']['read_known_keys_s']:.3f} s"),
             ""]
    if all("nightly" in d for d in inst.values()):
        def night(which: str, field: str, fmt: str = ","):
            return lambda d: format(d["nightly"][which][field], fmt)

        lines += [f"## Nightly catch-up over {n:,} photos (measured: one real schedule evaluation each)", "",
                  "`nightly_catch_up.evaluate_tick` end to end: the partitions read from the instance, the status "
                  "of every photo (photo hash + six manifests), the run requests. First night: the photo-hash "
                  "cache is empty, every photo is hashed; next night: the cache is warm (the usual case).", "",
                  head, rule,
                  row("first night: wall time", lambda d: _s(d["nightly"]["first_night"]["wall_s"])),
                  row("first night: ms per photo", night("first_night", "ms_per_photo", ".2f")),
                  row("first night: under 60 s", lambda d: _ok(d["nightly"]["first_night"]["wall_s"])),
                  row("next night: wall time", lambda d: _s(d["nightly"]["next_night"]["wall_s"])),
                  row("next night: ms per photo", night("next_night", "ms_per_photo", ".2f")),
                  row("next night: under 60 s", lambda d: _ok(d["nightly"]["next_night"]["wall_s"])),
                  row(f"photos up to date (must be {n:,})", night("next_night", "photos_up_to_date")),
                  row("run requests", night("next_night", "run_requests")), ""]
        st = result["store"]
        lines += [f"Store clone: {st['files_per_photo']} files per photo; {st['hardlinked_files']:,} hardlinks, "
                  f"{st['manifests_written']:,} manifests written for their key, rewritten outputs (the clone's "
                  f"photo path): {', '.join(st['rewritten_outputs']) or 'none'}; every byte of {st['verified_photos']} "
                  f"clones verified against their manifests; {st['clone_s']} s.", ""]
    return "\n".join(lines)


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--files", type=int, default=10_000, help="photo files in the folder (= partitions)")
    parser.add_argument("--cap", type=int, default=100, help="photos added per sensor tick")
    parser.add_argument("--instance", choices=("sqlite", "postgres", "both"), default="both")
    parser.add_argument("--store", type=Path, default=Path("outputs/demo"), help="a finished store (make demo)")
    parser.add_argument("--photos", type=Path, default=Path("examples/photos"), help="the store's photos")
    parser.add_argument("--source-key", default=None, help="the finished photo to clone (default: the first)")
    parser.add_argument("--preset", default="draft")
    parser.add_argument("--no-nightly", action="store_true", help="sensor only (no store needed)")
    parser.add_argument("--name", default="sensor_scale_10k")
    args = parser.parse_args()
    if args.files <= args.cap:
        parser.error("--files must be larger than --cap")
    kinds = ["sqlite", "postgres"] if args.instance == "both" else [args.instance]
    nightly = not args.no_nightly
    if nightly:
        key, photo = source_photo(args.store, args.photos, args.preset, args.source_key)
    else:
        key, photo = "", sorted(p for p in args.photos.iterdir() if p.suffix.lower() in (".jpg", ".png"))[0]
    load = "/".join(f"{x:.1f}" for x in os.getloadavg())
    # Under the store's parent: the hardlinks need one filesystem.
    root = Path(tempfile.mkdtemp(prefix="sensor_scale_", dir=args.store.resolve().parent if nightly else None))
    try:
        folder, store_root = root / "photos", root / "store"
        write_s = make_photo_folder(folder, args.files, photo)
        store: dict = {}
        if nightly:
            photos = {k: folder / name for k, name in photo_folder.scan(folder).items()}
            store = {**clone_store(args.store, key, photo, store_root, photos), "source_store": str(args.store)}
            print(f"store: {store}", flush=True)
        else:
            store_root.mkdir()
        instances = {k: bench_instance(k, root, folder, store_root, args.files, args.cap, args.preset, nightly)
                     for k in kinds}
    finally:
        shutil.rmtree(root, ignore_errors=True)
    result = {"date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "machine": platform.node(),
              "cpu_count": os.cpu_count(), "cpu_model": _cpu_model(), "load_average_at_start": load,
              "python": platform.python_version(), "dagster": dg.__version__, "postgres": _postgres_version(),
              "command": "python -m benchmarks.sensor_scale " + " ".join(sys.argv[1:]),
              "files": args.files, "cap_per_tick": args.cap, "preset": args.preset,
              "load_average_at_end": "/".join(f"{x:.1f}" for x in os.getloadavg()),
              "write_files_s": round(write_s, 1), "store": store, "instances": instances}
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{args.name}.json").write_text(json.dumps(result, indent=2) + "\n")
    text = markdown(result)
    (RESULTS / f"{args.name}.md").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
