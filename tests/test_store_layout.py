"""Stores and Dagster history from before every stage had one id are read after the renaming: the
finished outputs are found (cached, not re-run), checkpoints move along, and the migration is
idempotent, resumable and safe under concurrent openers."""

from __future__ import annotations

import json
import os
import shutil
import threading
from pathlib import Path

import dagster as dg
import pytest

from assets_store.hashing import bytes_sha256, config_hash
from assets_store.manifest import MANIFEST_FILE, Manifest
from assets_store.store import CHECKPOINTS_DIR, Store
from ops.engine.config_tree import from_dict
from ops.engine.early_stop import whole_schedule_record
from ops.engine.priors import PriorsConfig
from ops.engine.store_layout import (
    CONFIG_CHANGES,
    LAYOUT,
    LAYOUT_FILE,
    layout_of,
    migrate,
    open_store,
)
from ops.migrations import RENAMED_ASSETS, RENAMED_STAGES
from ops.pipeline.photo_run import PhotoRun
from ops.pipeline.runner import Pipeline, stages_until
from ops.stages import STAGE_IDS
from ops.stages.bake import BakeStageConfig
from ops.stages.dmtet import DMTetStageConfig
from ops.stages.nerf import NerfStageConfig
from ops.stages.qa import QAConfig
from ops.stages.texture import TextureStageConfig
from orchestration.history import migrate_history
from tests.pipeline_helpers import PHOTOS, output_hashes, tiny_config

KEY = "mug.jpg"
FIXTURE = Path(__file__).parent / "fixtures" / "store_layout1"  # manifests written by the code of 05c7323
OLD_NAME = {new: old for old, new in RENAMED_STAGES.items()}
CFG = tiny_config()


def _downgrade(store: Store) -> None:
    """Rewrite a current store the way the code before the renaming laid it out (layout 1)."""
    for photo in (store.photo_dir(k) for k in store.keys()):
        for folder in sorted(p for p in photo.iterdir() if (p / MANIFEST_FILE).is_file()):
            data = json.loads((folder / MANIFEST_FILE).read_text())
            data["stage"] = OLD_NAME.get(data["stage"], data["stage"])
            fp = data["fingerprint"]
            fp["inputs"] = {OLD_NAME.get(k, k): v for k, v in fp["inputs"].items()}
            for change in reversed(CONFIG_CHANGES):
                if folder.name in change.stages:
                    assert change.backward(data["config"]), (folder.name, change)
            fp["config_hash"] = config_hash(data["config"])
            (folder / MANIFEST_FILE).write_text(json.dumps(data))
            folder.rename(photo / data["stage"])
        ckpt = photo / CHECKPOINTS_DIR
        for new, old in OLD_NAME.items():
            if (ckpt / new).is_dir():
                (ckpt / new).rename(ckpt / old)
    (store.root / LAYOUT_FILE).unlink(missing_ok=True)


@pytest.fixture(scope="module")
def current(tmp_path_factory: pytest.TempPathFactory) -> Store:
    store = open_store(tmp_path_factory.mktemp("current"))
    outcome = Pipeline(store, CFG, "tiny").run([(PHOTOS / "mug.jpg", KEY)])[0]
    assert outcome.error is None, outcome.error
    return store


@pytest.fixture
def old_store(current: Store, tmp_path: Path) -> Store:
    shutil.copytree(current.root, tmp_path / "old")
    store = Store(tmp_path / "old")
    _downgrade(store)
    assert layout_of(store.root) == 1 and (store.photo_dir(KEY) / "nerf_fit").is_dir()
    return store


def test_a_store_from_before_is_read_cached_with_the_same_outputs(current: Store, old_store: Store) -> None:
    store = open_store(old_store.root)
    assert layout_of(store.root) == LAYOUT
    assert sorted(p.name for p in store.photo_dir(KEY).iterdir() if not p.name.startswith(".")) == sorted(
        STAGE_IDS)
    again = Pipeline(store, CFG, "tiny").run([(PHOTOS / "mug.jpg", KEY)])[0]
    assert [s.status for s in again.stages] == ["cached"] * len(STAGE_IDS), again
    for stage in STAGE_IDS:
        assert output_hashes(store, KEY, stage) == output_hashes(current, KEY, stage)
        m = store.read_manifest(KEY, stage)
        assert m is not None and config_hash(m.config) == m.fingerprint.config_hash


@pytest.mark.parametrize("stage", ["nerf", "dmtet"])
def test_an_interrupted_stage_resumes_from_its_layout1_checkpoint(current: Store, tmp_path: Path, stage: str) -> None:
    shutil.copytree(current.root, tmp_path / "old")
    store = Store(tmp_path / "old")
    later = STAGE_IDS[STAGE_IDS.index(stage):]
    run = PhotoRun(PHOTOS / "mug.jpg", KEY, store, CFG, "tiny", None, None, None)
    planned = run.planned(stage)
    for s in later:  # interrupted in ``stage``: its checkpoint is all there is of it
        shutil.rmtree(store.stage_dir(KEY, s))
    # Where the code before the renaming kept it: old input names, the layout-1 spelling of the config.
    old_config = whole_schedule_record(run.config_record(planned))  # layout 1 predates early stopping
    for change in reversed(CONFIG_CHANGES):
        if stage in change.stages:
            change.backward(old_config)
    old_inputs = {OLD_NAME.get(k, k): v for k, v in planned.fingerprint.inputs.items()}
    old_dir = (store.photo_dir(KEY) / CHECKPOINTS_DIR / OLD_NAME.get(stage, stage) / config_hash(old_config)[:12]
               / bytes_sha256(repr(sorted(old_inputs.items())).encode())[:12])
    old_dir.mkdir(parents=True)
    (old_dir / "step_000004.safetensors").write_bytes(b"state")
    _downgrade(store)
    assert not migrate(store).problems
    resume_at = run.checkpoint_path(planned)
    assert not resume_at.exists(), "the checkpoint folder's name changed with the layout"
    assert run.adopt_layout1_checkpoint(planned)
    assert (resume_at / "step_000004.safetensors").read_bytes() == b"state"
    assert not run.adopt_layout1_checkpoint(planned)
    # The pipeline does the same before it starts a stage: run it from the layout-1 folder once more.
    legacy = store.checkpoint_dir(KEY, stage) / old_dir.parent.name / old_dir.name  # moved with its stage folder
    os.replace(resume_at, legacy)
    outcome = Pipeline(store, CFG, "tiny").run([(PHOTOS / "mug.jpg", KEY)], stages_until(stage))[0]
    assert [s.status for s in outcome.stages][-1] == "resumed", outcome  # (the fake step file is then skipped)


def test_the_migration_is_idempotent_and_finishes_after_an_interruption(old_store: Store) -> None:
    photo = old_store.photo_dir(KEY)
    (photo / "uv_bake").rename(photo / "bake")  # killed after its first rename
    first = migrate(old_store)
    assert first.folders_renamed == 2 and first.manifests_rewritten == len(STAGE_IDS) - 1  # all but reference
    assert not first.problems
    second = migrate(old_store)
    assert (second.folders_renamed, second.manifests_rewritten, second.checkpoints_moved) == (0, 0, 0)
    assert all(old_store.read_manifest(KEY, s) is not None for s in ("nerf", "texture", "bake"))


def test_a_folder_under_both_names_keeps_the_current_one_and_says_so(old_store: Store) -> None:
    photo = old_store.photo_dir(KEY)
    shutil.copytree(photo / "nerf_fit", photo / "nerf")
    report = migrate(old_store)
    assert any("nerf_fit/ and nerf/" in p for p in report.problems)
    assert (photo / "nerf_fit").is_dir() and old_store.read_manifest(KEY, "nerf") is not None


def test_concurrent_openers_migrate_once(old_store: Store) -> None:
    barrier, stores, errors = threading.Barrier(3), [], []

    def opener() -> None:
        try:
            barrier.wait()
            stores.append(open_store(old_store.root))
        except Exception as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=opener) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and len(stores) == 3
    assert all(old_store.read_manifest(KEY, s) is not None for s in ("nerf", "texture", "bake"))


def test_manifests_written_by_the_old_code_become_current_configs(tmp_path: Path) -> None:
    shutil.copytree(FIXTURE, tmp_path / "store")
    store = Store(tmp_path / "store")
    for folder in (tmp_path / "store" / KEY).iterdir():  # the outputs themselves are not needed here
        for name, record in json.loads((folder / MANIFEST_FILE).read_text())["outputs"].items():
            if not (folder / name).exists():
                with open(folder / name, "wb") as fh:
                    fh.truncate(record["size"])
    store = open_store(store.root)
    classes = {"nerf": NerfStageConfig, "dmtet": DMTetStageConfig, "texture": TextureStageConfig,
               "bake": BakeStageConfig, "qa": QAConfig}
    for stage, cls in classes.items():
        m = store.read_manifest(KEY, stage)
        assert m is not None and m.stage == stage
        assert not set(m.fingerprint.inputs) & set(RENAMED_STAGES)
        assert config_hash(m.config) == m.fingerprint.config_hash
        parsed = from_dict(cls, m.config[stage])  # the recorded settings are valid current settings
        assert isinstance(parsed, cls)
        if "priors" in m.config:
            assert from_dict(PriorsConfig, m.config["priors"]).lora.rank == 4
    assert Manifest.from_json((store.stage_dir(KEY, "dmtet") / MANIFEST_FILE).read_text()).config["dmtet"][
        "texture_field"]


def test_dagster_history_of_the_old_asset_keys_shows_under_the_stage_ids(current: Store) -> None:
    instance = dg.DagsterInstance.ephemeral()
    for old in RENAMED_ASSETS:
        for partition in (KEY, "gone.jpg"):  # gone.jpg: the store no longer holds its outputs
            instance.report_runless_asset_event(dg.AssetMaterialization(asset_key=old, partition=partition))
    carried = migrate_history(instance, current)
    assert carried == dict.fromkeys(RENAMED_ASSETS.values(), 1)
    for new in RENAMED_ASSETS.values():
        assert instance.get_materialized_partitions(dg.AssetKey(new)) == {KEY}
        event = instance.get_latest_materialization_event(dg.AssetKey(new))
        assert event is not None and event.asset_materialization.metadata["migrated_from"].value in RENAMED_ASSETS
    assert migrate_history(instance, current) == dict.fromkeys(RENAMED_ASSETS.values(), 0)


def test_catalog_rows_from_before_read_under_the_stage_ids(tmp_path: Path) -> None:
    import datetime as dt

    from assets_store.catalog import Catalog
    from ops.reporting.report import build_report
    from ops.reporting.stage_columns import current_column, current_stage_columns

    when = dt.datetime(2026, 11, 30, tzinfo=dt.timezone.utc)
    old = {"run_id": "r1", "photo_key": "a.jpg", "created_at": when, "status": "ok", "nerf_fit_wall_s": 3.0,
           "uv_bake_status": "ran", "check_texture_refine_stable_optimisation": "pass", "runlog_nerf_fit": "a/x"}
    new = {"run_id": "r2", "photo_key": "b.jpg", "created_at": when + dt.timedelta(hours=1), "status": "ok",
           "nerf_wall_s": 5.0, "bake_status": "cached"}
    catalog = Catalog(tmp_path / ".catalog")
    catalog.append([old])
    catalog.append([new])
    table = current_stage_columns(catalog.read())
    assert not {"nerf_fit_wall_s", "uv_bake_status", "runlog_nerf_fit"} & set(table.column_names)
    rows = {r["photo_key"]: r for r in table.to_pylist()}
    assert rows["a.jpg"]["nerf_wall_s"] == 3.0 and rows["b.jpg"]["nerf_wall_s"] == 5.0
    assert rows["a.jpg"]["bake_status"] == "ran" and rows["a.jpg"]["check_texture_stable_optimisation"] == "pass"
    assert rows["a.jpg"]["runlog_nerf"] == "a/x"
    assert current_column("metric_ref_psnr") == "metric_ref_psnr" and current_column("dmtet_wall_s") == "dmtet_wall_s"
    page = build_report(catalog)
    assert "nerf_fit" not in page and "uv_bake" not in page
