"""The folder sensor, the upload-completeness rules and the photo hash cache, on temporary folders."""

from __future__ import annotations

import io
import json
import os
import time
from pathlib import Path

import dagster as dg
import numpy as np
import pytest
from PIL import Image

from assets_store.photo_hashes import PhotoHashes
from ops.intake import photo_folder
from orchestration.definitions import build_definitions
from orchestration.partitions import PHOTOS
from orchestration.settings import OrchestrationSettings


def _image_bytes(fmt: str, seed: int) -> bytes:
    rng = np.random.default_rng(seed)
    buf = io.BytesIO()
    Image.fromarray(rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)).save(buf, format=fmt)
    return buf.getvalue()


def _write(folder: Path, name: str, data: bytes, age_s: float = 3600.0) -> Path:
    path = folder / name
    path.write_bytes(data)
    past = time.time() - age_s
    os.utime(path, (past, past))
    return path


def _tick(defs: dg.Definitions, instance: dg.DagsterInstance, cursor: str | None = None) -> dg.SensorResult:
    sensor = defs.resolve_sensor_def("photo_folder_sensor")
    context = dg.build_sensor_context(instance=instance, cursor=cursor,
                                      resources={"morpheus": defs.resources["morpheus"]})
    result = sensor(context)
    for request in result.dynamic_partitions_requests or []:  # what the daemon does with the result
        instance.add_dynamic_partitions(request.partitions_def_name, list(request.partition_keys))
    return result


@pytest.fixture
def folder_defs(tmp_path: Path):
    folder = tmp_path / "photos"
    folder.mkdir()

    def make(**changes: object) -> dg.Definitions:
        base = {"photo_dir": str(folder), "store_root": str(tmp_path / "store"), "settle_seconds": 60.0}
        return build_definitions(settings=OrchestrationSettings(**{**base, **changes}))

    with dg.instance_for_test() as instance:
        yield folder, make, instance


def test_sensor_adds_complete_photos_and_ignores_the_rest(folder_defs) -> None:
    folder, make, instance = folder_defs
    defs = make()
    _write(folder, "shoe.jpg", _image_bytes("JPEG", 1))
    _write(folder, "lamp.png", _image_bytes("PNG", 2))
    _write(folder, "notes.txt", b"not a photo")
    _write(folder, "chair.jpg.part", _image_bytes("JPEG", 3))
    _write(folder, ".vase.jpg.x8F2a", _image_bytes("JPEG", 4))
    _write(folder, "cut.jpg", _image_bytes("JPEG", 5)[:-300])  # old but truncated: still uploading
    _write(folder, "fresh.png", _image_bytes("PNG", 6), age_s=1.0)  # complete but just written
    (folder / "sub.jpg").mkdir()  # a folder with a photo's name is not a photo

    first = _tick(defs, instance)
    assert sorted(r.partition_key for r in first.run_requests) == ["lamp.png", "shoe.jpg"]
    assert sorted(instance.get_dynamic_partitions(PHOTOS)) == ["lamp.png", "shoe.jpg"]
    cursor = json.loads(first.cursor)
    assert cursor["waiting"] == ["cut.jpg", "fresh.png"]

    second = _tick(defs, instance, first.cursor)
    assert not second.run_requests
    assert "2 new file(s) still uploading" in second.skip_reason.skip_message

    _write(folder, "cut.jpg", _image_bytes("JPEG", 5))  # the upload finished
    os.utime(folder / "fresh.png", (time.time() - 120, time.time() - 120))
    third = _tick(defs, instance, second.cursor)
    assert sorted(r.partition_key for r in third.run_requests) == ["cut.jpg", "fresh.png"]

    fourth = _tick(defs, instance, third.cursor)
    assert not fourth.run_requests and fourth.skip_reason.skip_message == "no new photos"


def test_sensor_caps_new_photos_per_tick(folder_defs) -> None:
    folder, make, instance = folder_defs
    defs = make(sensor_max_new_per_tick=3)
    for i in range(7):
        _write(folder, f"item_{i}.png", _image_bytes("PNG", i))
    added = []
    for _ in range(3):
        result = _tick(defs, instance)
        assert all(r.run_key == f"new:{r.partition_key}" for r in result.run_requests)
        added.append(sorted(r.partition_key for r in result.run_requests or []))
    assert [len(a) for a in added] == [3, 3, 1]
    assert sorted(k for keys in added for k in keys) == [f"item_{i}.png" for i in range(7)]
    assert not _tick(defs, instance).run_requests


def test_unsafe_names_get_safe_keys(folder_defs) -> None:
    folder, make, instance = folder_defs
    _write(folder, "Café, crème….jpg", _image_bytes("JPEG", 9))
    result = _tick(make(), instance)
    (key,) = [r.partition_key for r in result.run_requests]
    assert "," not in key and "..." not in key and key.isascii()
    assert make().resources["morpheus"].photo_path(key) == folder / "Café, crème….jpg"


def test_missing_folder_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="MORPHEUS_PHOTO_DIR"):
        photo_folder.scan(tmp_path / "nope")


def test_upload_state_rules(tmp_path: Path) -> None:
    png = _write(tmp_path, "a.png", _image_bytes("PNG", 1))
    assert photo_folder.upload_state(png, 30.0).ready
    cut = _write(tmp_path, "b.png", _image_bytes("PNG", 1)[:-5])
    assert "incomplete" in photo_folder.upload_state(cut, 30.0).reason
    young = _write(tmp_path, "c.png", _image_bytes("PNG", 1), age_s=2.0)
    assert "settle" in photo_folder.upload_state(young, 30.0).reason
    assert photo_folder.upload_state(young, 0.0).ready
    empty = _write(tmp_path, "d.webp", b"")
    assert not photo_folder.upload_state(empty, 0.0).ready
    assert not photo_folder.upload_state(tmp_path / "gone.png", 0.0).ready
    assert not photo_folder.is_photo_name("x.JPG.crdownload") and photo_folder.is_photo_name("X.JPG")


def test_photo_hashes_rehash_only_changed_files(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import assets_store.photo_hashes as module

    photo = _write(tmp_path, "p.png", _image_bytes("PNG", 1))
    calls = []
    real = module.file_sha256
    monkeypatch.setattr(module, "file_sha256", lambda p: calls.append(p) or real(p))
    cache = PhotoHashes(tmp_path / "store")
    first = cache.sha256(photo)
    cache.save()
    again = PhotoHashes(tmp_path / "store")
    assert again.sha256(photo) == first and len(calls) == 1
    _write(tmp_path, "p.png", _image_bytes("PNG", 2))
    assert again.sha256(photo) != first and len(calls) == 2
    (tmp_path / "store" / module.CACHE_FILE).write_text("{broken")
    assert PhotoHashes(tmp_path / "store").sha256(photo) == real(photo)


def test_settings_from_environment() -> None:
    s = OrchestrationSettings.from_env({"MORPHEUS_SET": "nerf.loop.steps=10; qa.min_ref_psnr=12",
                                        "MORPHEUS_BATCH": "4", "MORPHEUS_PHOTO_DIR": "/data/photos"})
    assert s.overrides == ("nerf.loop.steps=10", "qa.min_ref_psnr=12")
    assert s.backfill_batch == 4 and s.photo_dir == "/data/photos"
    with pytest.raises(ValueError, match="MORPHEUS_BATCH"):
        OrchestrationSettings.from_env({"MORPHEUS_BATCH": "lots"})
    with pytest.raises(ValueError, match="MORPHEUS_BATCH"):
        OrchestrationSettings.from_env({"MORPHEUS_BATCH": "0"})
    with pytest.raises(ValueError, match="MORPHEUS_EXECUTOR"):
        OrchestrationSettings.from_env({"MORPHEUS_EXECUTOR": "threads"})
