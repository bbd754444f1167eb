"""Stores and Dagster history from before every stage had one id are read after the renaming: the
finished outputs are found (cached, not re-run), checkpoints move along, and the migration is
idempotent, resumable and safe under concurrent openers."""

from __future__ import annotations

import json
import shutil
import threading
from pathlib import Path

import dagster as dg
import pytest

from assets_store.hashing import config_hash
from assets_store.manifest import MANIFEST_FILE, Manifest
from assets_store.store import CHECKPOINTS_DIR, Store
from ops.config.tree import from_dict
from ops.engine.pipeline import PhotoRun, run_photo
from ops.engine.stage_ids import RENAMED_STAGES
from ops.engine.store_layout import LAYOUT, LAYOUT_FILE, RENAMED_CONFIG, layout_of, migrate, open_store
from ops.stages.bake import BakeStageConfig
from ops.stages.dmtet import DMTetStageConfig
from ops.stages.nerf import NerfStageConfig
from ops.stages.qa import QAConfig
from ops.stages.texture import TextureStageConfig
from orchestration.history import RENAMED_ASSETS, migrate_history
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
            for old, new in RENAMED_CONFIG.get(folder.name, ()):
                group = data["config"][new[0]]
                group[old[-1]] = group.pop(new[-1])
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
    outcome = run_photo(PHOTOS / "mug.jpg", store, CFG, "tiny", KEY)
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
        ["reference", "nerf", "dmtet", "texture", "bake", "qa"])
    again = run_photo(PHOTOS / "mug.jpg", store, CFG, "tiny", KEY)
    assert [s.status for s in again.stages] == ["cached"] * 6, again
    for stage in ("reference", "nerf", "dmtet", "texture", "bake", "qa"):
        assert output_hashes(store, KEY, stage) == output_hashes(current, KEY, stage)
        m = store.read_manifest(KEY, stage)
        assert m is not None and config_hash(m.config) == m.fingerprint.config_hash


def test_an_interrupted_nerf_stage_resumes_from_its_checkpoint_after_the_migration(current: Store,
                                                                                      tmp_path: Path) -> None:
    shutil.copytree(current.root, tmp_path / "old")
    store = Store(tmp_path / "old")
    run = PhotoRun(PHOTOS / "mug.jpg", KEY, store, CFG, "tiny", None, None, None)
    resume_at = run.checkpoint_path(run.planned("nerf"))
    for stage in ("nerf", "dmtet", "texture", "bake", "qa"):  # interrupted in the NeRF stage
        shutil.rmtree(store.stage_dir(KEY, stage))
    resume_at.mkdir(parents=True)
    (resume_at / "step_000004.safetensors").write_bytes(b"state")
    _downgrade(store)
    assert (store.photo_dir(KEY) / CHECKPOINTS_DIR / "nerf_fit").is_dir()
    report = migrate(store)
    assert report.checkpoints_moved == 1 and not report.problems
    assert (resume_at / "step_000004.safetensors").read_bytes() == b"state"


def test_the_migration_is_idempotent_and_finishes_after_an_interruption(old_store: Store) -> None:
    photo = old_store.photo_dir(KEY)
    (photo / "uv_bake").rename(photo / "bake")  # killed after its first rename
    first = migrate(old_store)
    assert first.folders_renamed == 2 and first.manifests_rewritten == 5 and not first.problems  # all but reference
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
