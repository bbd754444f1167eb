"""The Dagster layer end to end on CPU: six assets materialised for a bundled photo in a temporary
instance, checks and metadata, caching, the nightly schedule (missing / stale only), the photo
observation (a changed photo changes only its own data version), a batch with a failing photo
resumed from its checkpoint, and the code location validating through the `dagster` command."""

from __future__ import annotations

import base64
import io
import os
import re
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path

import dagster as dg
import pytest
import trimesh
from PIL import Image

from assets_store.catalog import Catalog
from assets_store.checkpoints import Checkpoints
from assets_store.store import Store
from ops.engine.checks import read_report
from ops.stages import CHECKS, STAGE_IDS
from orchestration.assets import GPU_POOL
from orchestration.definitions import JOB
from orchestration.partitions import PHOTOS
from tests.orchestration_helpers import (
    build,
    check_evaluations,
    inject_fault,
    materializations,
    photo_folder,
    run_job,
)
from tests.pipeline_helpers import ROOT, manifest

KEY = "mug.jpg"


@pytest.fixture(scope="module")
def deployment(tmp_path_factory: pytest.TempPathFactory):
    root = tmp_path_factory.mktemp("dagster")
    photo_folder(root, [KEY, "bottle.jpg"])
    home = root / "home"
    home.mkdir()
    with dg.instance_for_test(temp_dir=str(home)) as instance:
        defs = build(root)
        first = run_job(defs, instance, [KEY])
        yield root, defs, instance, first


def _preview_png(md: dg.MetadataValue) -> Image.Image:
    match = re.search(r"data:image/png;base64,([A-Za-z0-9+/=]+)\)", md.value)
    assert match, "no inline base64 PNG in the preview metadata"
    return Image.open(io.BytesIO(base64.b64decode(match.group(1))))


def test_all_six_assets_materialise_with_metadata_and_checks(deployment) -> None:
    root, _, _, result = deployment
    assert result.success
    mats = materializations(result)
    assert {a for a, p in mats if p == KEY} == set(STAGE_IDS)
    for stage in STAGE_IDS:
        asset, meta = stage, mats[(stage, KEY)]
        for field in ("wall_time_s", "device", "preset", "cache_hit", "status", "metrics", "stage_dir", "prior"):
            assert field in meta, f"{asset} lacks {field}"
        assert meta["cache_hit"].value is False
        assert meta["preset"].value == "draft" and meta["device"].value == "cpu"
        preview = _preview_png(meta["preview"])
        assert preview.width > 16 and preview.height > 16, f"{asset}: empty preview"
        assert Path(meta["stage_dir"].value) == Store(root / "store").stage_dir(KEY, stage)
    assert "plan" in mats[("dmtet", KEY)]
    glb = Path(mats[("bake", KEY)]["glb"].value)
    loaded = trimesh.load(glb, force="mesh")
    assert len(loaded.faces) > 0 and loaded.visual.uv is not None

    evaluations = check_evaluations(result)
    seen = {(e.asset_key.to_user_string(), e.check_name) for e in evaluations}
    expected = {(s, c.name) for s, specs in CHECKS.items() for c in specs}
    assert seen == expected
    assert all(e.partition == KEY for e in evaluations)
    # The checks agree with the QA stage's own report, failures included.
    report = read_report(Store(root / "store").stage_dir(KEY, "qa"))
    verdict = next(e for e in evaluations if e.check_name == "verdict")
    assert verdict.passed == (report.verdict != "fail")
    assert verdict.description
    rows = [r for r in Catalog(Store(root / "store").catalog_dir).read().to_pylist() if r["run_id"] == result.run_id]
    assert len(rows) == 1 and rows[0]["photo_key"] == KEY and rows[0]["verdict"] == report.verdict
    assert rows[0]["status"] == "ok" and rows[0]["qa_status"] == "ran" and rows[0]["nerf_device"] == "cpu"


def test_rerun_is_all_cache_hits(deployment) -> None:
    root, defs, instance, first = deployment
    again = run_job(defs, instance, [KEY])
    assert again.success
    assert {a: m["cache_hit"].value for (a, p), m in materializations(again).items() if p == KEY} == \
        dict.fromkeys(STAGE_IDS, True)
    # The catalog records the re-run without its predecessor's work (tests/test_report_work.py: the report).
    rows = {r["run_id"]: r for r in Catalog(Store(root / "store").catalog_dir).read().to_pylist()}
    assert rows[again.run_id]["status"] == "cached" and rows[again.run_id]["work_s"] == 0 < rows[first.run_id]["work_s"]
    assert {rows[again.run_id][f"{s}_status"] for s in STAGE_IDS} == {"cached"}


def _schedule_requests(defs: dg.Definitions, instance: dg.DagsterInstance) -> dict[str, str]:
    schedule = defs.resolve_schedule_def("nightly_catch_up")
    context = dg.build_schedule_context(instance=instance, resources={"morpheus": defs.resources["morpheus"]},
                                        scheduled_execution_time=datetime(2026, 11, 24, 2, tzinfo=timezone.utc))
    result = schedule(context)
    if isinstance(result, dg.SkipReason):
        return {}
    return {r.partition_key: r.tags["morpheus/reason"] for r in result}


def _observed_versions(defs: dg.Definitions, instance: dg.DagsterInstance) -> dict[str, str]:
    source = next(a for a in defs.assets if isinstance(a, dg.SourceAsset))
    from dagster._core.definitions.observe import observe  # what the UI's "Observe sources" button runs

    result = observe([source], instance=instance, resources={"morpheus": defs.resources["morpheus"]})
    return {e.event_specific_data.asset_observation.partition:
            e.event_specific_data.asset_observation.tags["dagster/data_version"]
            for e in result.all_events if e.event_type_value == "ASSET_OBSERVATION"}


def test_schedule_requests_only_missing_and_stale(deployment) -> None:
    root, defs, instance, _ = deployment
    photo = root / "photos" / KEY
    original, stat = photo.read_bytes(), photo.stat()
    assert _schedule_requests(defs, instance) == {}, "a fresh catalog must request nothing"
    instance.add_dynamic_partitions(PHOTOS, ["bottle.jpg"])
    assert _schedule_requests(defs, instance) == {"bottle.jpg": "missing"}

    before = _observed_versions(defs, instance)
    try:
        img = Image.open(photo).convert("RGB")
        img.putpixel((3, 3), (255 - img.getpixel((3, 3))[0], 0, 0))
        img.save(photo, quality=95)
        assert _schedule_requests(defs, instance) == {"bottle.jpg": "missing", KEY: "stale"}
        after = _observed_versions(defs, instance)
        assert after[KEY] != before[KEY], "a changed photo must get a new data version"
        assert after["bottle.jpg"] == before["bottle.jpg"], "an unchanged photo keeps its data version"
    finally:
        photo.write_bytes(original)
        os.utime(photo, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert _schedule_requests(defs, instance) == {"bottle.jpg": "missing"}


def test_config_change_makes_photos_stale(deployment) -> None:
    root, _, instance, _ = deployment
    changed = build(root, overrides=(*build(root).resources["morpheus"].overrides, "qa.min_mask_iou=0.5"))
    assert _schedule_requests(changed, instance).get(KEY) == "stale"


def test_definitions_shape(deployment) -> None:
    _, defs, _, _ = deployment
    graph = defs.resolve_asset_graph()
    names = {k.to_user_string() for k in graph.get_all_asset_keys()}
    assert names >= {"photo_files", *STAGE_IDS}
    assert graph.get(dg.AssetKey("reference")).parent_keys == {dg.AssetKey("photo_files")}
    assert dg.AssetKey("nerf") in graph.get(dg.AssetKey("dmtet")).parent_keys
    assert graph.get(dg.AssetKey("qa")).parent_keys == {dg.AssetKey(s) for s in STAGE_IDS[:-1]}
    for asset in defs.assets:
        if isinstance(asset, dg.AssetsDefinition):
            key = asset.key.to_user_string()
            assert asset.partitions_def is not None and asset.partitions_def.name == PHOTOS
            assert asset.code_versions_by_key[asset.key], f"{key} has no code version"
            assert asset.op.retry_policy is not None
            assert asset.backfill_policy is not None and asset.backfill_policy.max_partitions_per_run == 8
            gpu = key in ("nerf", "dmtet", "texture")
            assert (asset.op.pool == GPU_POOL) == gpu
            assert ("dagster-k8s/config" in asset.op.tags) == gpu
    assert defs.resolve_job_def(JOB) is not None


def test_batch_with_a_failing_photo_resumes_from_its_checkpoint(tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """A backfill batch of two photos run one after the other (MORPHEUS_BATCH_TOGETHER=0); one
    crashes half-way through its NeRF stage. The other photo finishes the stage; re-executing from
    the failure resumes the crashed one at its checkpoint."""
    photo_folder(tmp_path, ["bottle.jpg", KEY])
    defs = build(tmp_path, batch_together=False)
    bad, good = "bottle.jpg", KEY
    fault_at = 5  # checkpoints every 2 steps: the newest one before the fault is at step 4
    monkeypatch.setenv("MORPHEUS_TEST_ROOT", str(tmp_path))
    monkeypatch.setenv("MORPHEUS_BATCH_TOGETHER", "0")
    home = tmp_path / "home"
    home.mkdir()
    with dg.instance_for_test(temp_dir=str(home)) as instance:
        fault = inject_fault(monkeypatch, f"{bad}:nerf", fault_at)
        first = run_job(defs, instance, [bad, good])
        assert not first.success
        mats = materializations(first)
        assert ("reference", bad) in mats and ("reference", good) in mats
        assert ("nerf", good) in mats, "the healthy photo's stage must be recorded"
        assert ("nerf", bad) not in mats
        failure = next(e for e in first.all_events if e.event_type_value == "STEP_FAILURE")
        error = failure.event_specific_data.error.to_string()
        assert "1 of 2 photos failed" in error and "injected fault" in error
        store = Store(tmp_path / "store")
        ckpt_dirs = [p for p in store.checkpoint_dir(bad, "nerf").rglob("*") if p.is_dir()]
        steps = sorted({s for d in ckpt_dirs for s in Checkpoints(d, keep=3).steps()})
        assert steps and max(steps) == fault_at - 1

        fault.disarm()
        options = dg.ReexecutionOptions.from_failure(first.run_id, instance)
        # An instance closed by an earlier test can leave Dagster's context-local state storage
        # pointing at it; loading the job for re-execution must see this test's instance.
        from dagster._core.storage.defs_state.base import set_defs_state_storage

        with set_defs_state_storage(instance.defs_state_storage):
            again = dg.execute_job(dg.reconstructable(_tiny_job), instance=instance, reexecution_options=options,
                                   tags={k: v for k, v in first.dagster_run.tags.items() if "partition_range" in k})
        assert again.success
        nerf = manifest(store, bad, "nerf")
        assert nerf.metrics["resumed_from_step"] == fault_at - 1
        assert nerf.metrics["steps_run"] == nerf.config["nerf"]["loop"]["steps"] - (fault_at - 1)
        assert manifest(store, good, "nerf").metrics["resumed_from_step"] is None
        for key in (bad, good):
            assert read_report(store.stage_dir(key, "qa")).verdict in ("pass", "warn", "fail")
        for asset in STAGE_IDS:
            assert instance.get_materialized_partitions(dg.AssetKey(asset)) >= {bad, good}, asset


def test_a_gpu_stage_step_optimises_its_photos_together(tmp_path: Path) -> None:
    """A backfill batch of three photos at the NeRF stage: the two with a reference run as one batch
    (one prior forward per step for both); the third, whose reference is missing, fails alone and
    at once (bad input: no retry), and the catalog records why."""
    keys = ["bottle.jpg", KEY, "box.jpg"]
    photo_folder(tmp_path, keys)
    defs = build(tmp_path, max_retries=1)
    home = tmp_path / "home"
    home.mkdir()
    with dg.instance_for_test(temp_dir=str(home)) as instance:
        assert run_job(defs, instance, keys[:2], assets=["reference"]).success
        result = run_job(defs, instance, keys, assets=["nerf"])
        assert not result.success
        assert not [e for e in result.all_events if e.event_type_value == "STEP_UP_FOR_RETRY"]
        store, mats = Store(tmp_path / "store"), materializations(result)
        for key in keys[:2]:
            assert manifest(store, key, "nerf").metrics["batch_size"] == 2
            assert mats[("nerf", key)]["metrics"].value["batch_size"] == 2
        assert ("nerf", "box.jpg") not in mats and store.read_manifest("box.jpg", "nerf") is None
        assert {e.partition for e in check_evaluations(result)} == set(keys[:2])
        failure = next(e for e in result.all_events if e.event_type_value == "STEP_FAILURE")
        error = failure.event_specific_data.error.to_string()
        assert "1 of 3 photos failed" in error and "box.jpg" in error and "MissingUpstreamError" in error
        (row,) = [r for r in Catalog(store.catalog_dir).read().to_pylist() if r["run_id"] == result.run_id]
        assert row["photo_key"] == "box.jpg" and row["status"] == "failed"
        assert "MissingUpstreamError" in row["failure_reason"]


def _tiny_job() -> dg.JobDefinition:
    """The job for ``execute_job`` (it must be importable by name): settings from the environment
    the failing test set up, i.e. the same temporary folder as the first run."""
    from orchestration.definitions import build_definitions
    from tests.orchestration_helpers import settings

    root = Path(os.environ["MORPHEUS_TEST_ROOT"])
    executor = os.environ.get("MORPHEUS_EXECUTOR", "in_process")
    together = os.environ.get("MORPHEUS_BATCH_TOGETHER", "1") != "0"
    return build_definitions(settings=settings(root, executor=executor, batch_together=together)).resolve_job_def(JOB)


def test_definitions_validate_with_the_dagster_command(tmp_path: Path) -> None:
    env = {**os.environ, "DAGSTER_HOME": str(tmp_path), "PYTHONPATH": str(ROOT)}
    dagster = Path(sys.executable).parent / "dagster"
    proc = subprocess.run([str(dagster), "definitions", "validate", "-w", "workspace.yaml"], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "passed validation" in proc.stdout + proc.stderr


def test_backfill_from_the_command_line_is_submitted(tmp_path: Path) -> None:
    """`dagster job backfill` over registered photos creates one backfill with exactly those keys."""
    photo_folder(tmp_path, [KEY, "bottle.jpg"])
    env = {**os.environ, "DAGSTER_HOME": str(tmp_path / "home"), "PYTHONPATH": str(ROOT),
           "MORPHEUS_PHOTO_DIR": str(tmp_path / "photos"), "MORPHEUS_STORE": str(tmp_path / "store")}
    (tmp_path / "home").mkdir()
    bindir = Path(sys.executable).parent
    added = subprocess.run([str(bindir / "morpheus3d-dagster"), "add-photos"], cwd=ROOT, env=env,
                           capture_output=True, text=True, timeout=300)
    assert added.returncode == 0, added.stderr
    assert added.stdout.strip() == f"bottle.jpg,{KEY}"
    proc = subprocess.run([str(bindir / "dagster"), "job", "backfill", "-w", "workspace.yaml", "-j", JOB,
                           "--partitions", added.stdout.strip(), "--noprompt"], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    with dg.DagsterInstance.from_config(str(tmp_path / "home")) as instance:
        backfills = instance.get_backfills()
        assert len(backfills) == 1
        assert sorted(backfills[0].partition_names) == ["bottle.jpg", KEY]


def test_transient_failure_is_retried_and_resumes_from_the_checkpoint(tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """The retry policy re-runs a stage that crashed half-way; the retry starts at the checkpoint."""
    photo_folder(tmp_path, [KEY])
    defs = build(tmp_path, max_retries=1)
    fault = inject_fault(monkeypatch, f"{KEY}:dmtet", 3, once=True)
    home = tmp_path / "home"
    home.mkdir()
    with dg.instance_for_test(temp_dir=str(home)) as instance:
        result = run_job(defs, instance, [KEY])
        assert result.success
        assert fault.fired == [3]
        retries = [e for e in result.all_events if e.event_type_value == "STEP_UP_FOR_RETRY"]
        assert [e.step_key for e in retries] == ["dmtet"]
        dmtet = manifest(Store(tmp_path / "store"), KEY, "dmtet")
        assert dmtet.metrics["resumed_from_step"] == 2  # dmtet checkpoints every 2 steps in the tiny config
        assert materializations(result)[("dmtet", KEY)]["resumed_from_step"].value == 2


def test_a_removed_photo_fails_at_once_without_retries(tmp_path: Path) -> None:
    photo_folder(tmp_path, [])
    defs = build(tmp_path, max_retries=2, retry_delay_s=30.0)
    home = tmp_path / "home"
    home.mkdir()
    with dg.instance_for_test(temp_dir=str(home)) as instance:
        result = run_job(defs, instance, ["gone.jpg"])
        assert not result.success
        assert not [e for e in result.all_events if e.event_type_value == "STEP_UP_FOR_RETRY"]
        failure = next(e for e in result.all_events if e.event_type_value == "STEP_FAILURE")
        message = failure.event_specific_data.error.to_string()
        assert "gone.jpg" in message and str(tmp_path / "photos") in message and "UnknownPhotoError" in message
        assert not (tmp_path / "store" / "gone.jpg" / "reference").exists()
        (row,) = Catalog(Store(tmp_path / "store").catalog_dir).read().to_pylist()
        assert row["status"] == "failed" and "UnknownPhotoError" in row["failure_reason"]


def test_multiprocess_executor_runs_a_stage_in_a_child_process(tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    from dagster._core.storage.defs_state.base import set_defs_state_storage

    photo_folder(tmp_path, [KEY])
    monkeypatch.setenv("MORPHEUS_TEST_ROOT", str(tmp_path))
    monkeypatch.setenv("MORPHEUS_EXECUTOR", "multiprocess")
    monkeypatch.setenv("PYTHONPATH", str(ROOT))
    home = tmp_path / "home"
    home.mkdir()
    with dg.instance_for_test(temp_dir=str(home)) as instance, set_defs_state_storage(instance.defs_state_storage):
        instance.add_dynamic_partitions(PHOTOS, [KEY])
        result = dg.execute_job(dg.reconstructable(_tiny_job), instance=instance, tags={"dagster/partition": KEY},
                                asset_selection=[dg.AssetKey("reference")])
        assert result.success
        engine = " ".join(e.message or "" for e in result.all_events if e.event_type_value == "ENGINE_EVENT")
        assert "multiprocess" in engine.lower() or "subprocess" in engine.lower(), engine
        assert Store(tmp_path / "store").read_manifest(KEY, "reference") is not None
