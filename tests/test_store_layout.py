"""Store layout, manifests and atomic stage commits."""

from __future__ import annotations

import hashlib
import json
import math
import os
import random
import secrets
import subprocess
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path

import pytest

from assets_store.hashing import bytes_sha256, canonical_json, config_hash, file_sha256
from assets_store.keys import UnsafeKeyError
from assets_store.manifest import MANIFEST_FILE, FileRecord, Fingerprint, Manifest
from assets_store.store import STAGING_DIR, Store


def _fingerprint() -> Fingerprint:
    return Fingerprint(
        inputs={"photo": secrets.token_hex(32), "mask": secrets.token_hex(32)},
        config_hash=secrets.token_hex(32),
        code_version=secrets.token_hex(4),
    )


def _manifest(key: str, stage: str = "reference", fp: Fingerprint | None = None, **kw) -> Manifest:
    return Manifest(stage=stage, photo_key=key, fingerprint=fp or _fingerprint(), device="cpu", preset="fast",
                    prior="proxy (weight-free)", **kw)


def _commit(store: Store, key: str, files: dict[str, bytes], stage: str = "reference", **kw) -> Manifest:
    with store.stage_writer(key, stage) as w:
        for name, data in files.items():
            (w.path / name).parent.mkdir(parents=True, exist_ok=True)
            (w.path / name).write_bytes(data)
        return w.commit(_manifest(key, stage, **kw))


def _strict(text: str) -> object:
    def no_constants(name: str) -> None:
        raise AssertionError(f"non-standard JSON constant {name}")

    return json.loads(text, parse_constant=no_constants)


@pytest.fixture
def store(tmp_path: Path) -> Store:
    return Store(tmp_path / "store")


@pytest.fixture
def key() -> str:
    return f"mug-{secrets.token_hex(4)}.jpg"


def test_commit_makes_manifest_and_outputs_visible(store: Store, key: str) -> None:
    files = {"mesh.obj": os.urandom(3000), "views/front.png": os.urandom(1 << 21), "empty.txt": b""}
    manifest = _commit(store, key, files, metrics={"psnr": 31.5})
    folder = store.stage_dir(key, "reference")
    assert folder == store.root / key / "reference"
    assert set(manifest.outputs) == set(files)
    for name, data in files.items():
        assert (folder / name).read_bytes() == data
        assert manifest.outputs[name] == FileRecord(sha256=hashlib.sha256(data).hexdigest(), size=len(data))
    assert (folder / MANIFEST_FILE).is_file()
    assert store.read_manifest(key, "reference") == manifest
    assert store.verify(key, "reference")
    assert store.keys() == [key]
    assert not list((store.root / key / STAGING_DIR).glob("*"))


def test_recommit_replaces_the_whole_folder(store: Store, key: str) -> None:
    _commit(store, key, {"old_only.bin": b"old", "shared.bin": b"v1"})
    second = _commit(store, key, {"shared.bin": b"v2"})
    folder = store.stage_dir(key, "reference")
    assert sorted(p.name for p in folder.iterdir()) == [MANIFEST_FILE, "shared.bin"]
    assert store.read_manifest(key, "reference") == second
    assert sorted(p.name for p in folder.parent.iterdir() if p.name != STAGING_DIR) == ["reference"]
    assert list((folder.parent / STAGING_DIR).iterdir()) == []  # no aside or staging leftovers


def test_exception_in_with_keeps_previous_output_and_no_staging(store: Store, key: str) -> None:
    first = _commit(store, key, {"a.bin": b"first"})
    with pytest.raises(RuntimeError, match="boom"), store.stage_writer(key, "reference") as w:
        (w.path / "a.bin").write_bytes(b"second, half written")
        staging = w.path
        raise RuntimeError("boom")
    assert not staging.exists()
    assert not list((store.root / key / STAGING_DIR).glob("*"))
    assert store.read_manifest(key, "reference") == first
    assert (store.stage_dir(key, "reference") / "a.bin").read_bytes() == b"first"
    assert store.verify(key, "reference")


def test_writer_without_commit_leaves_nothing(store: Store, key: str) -> None:
    with store.stage_writer(key, "texture") as w:
        (w.path / "x.bin").write_bytes(b"x")
    assert not store.stage_dir(key, "texture").exists()
    assert store.read_manifest(key, "texture") is None
    assert not list((store.root / key / STAGING_DIR).glob("*"))


def test_commit_refuses_symlinks_and_foreign_manifests(store: Store, key: str, tmp_path: Path) -> None:
    outside = tmp_path / "outside.txt"
    outside.write_text("secret")
    with pytest.raises(ValueError, match="symlink"), store.stage_writer(key, "reference") as w:
        (w.path / "link.txt").symlink_to(outside)
        w.commit(_manifest(key))
    with pytest.raises(ValueError, match="writer for"), store.stage_writer(key, "reference") as w:
        w.commit(_manifest(key, stage="texture"))
    assert not store.stage_dir(key, "reference").exists()


def test_lookup_needs_an_equal_fingerprint(store: Store, key: str) -> None:
    fp = _fingerprint()
    _commit(store, key, {"a.bin": os.urandom(64)}, fp=fp)
    same = Fingerprint(inputs=dict(fp.inputs), config_hash=fp.config_hash, code_version=fp.code_version)
    assert store.lookup(key, "reference", same) is not None
    changed_input = {**fp.inputs, "mask": secrets.token_hex(32)}
    for other in [
        replace(fp, inputs=changed_input),
        replace(fp, inputs={**fp.inputs, "extra": secrets.token_hex(32)}),
        replace(fp, config_hash=secrets.token_hex(32)),
        replace(fp, code_version=fp.code_version + "-dirty"),
    ]:
        assert store.lookup(key, "reference", other) is None
    assert store.lookup(key, "geometry", same) is None


@pytest.mark.parametrize("damage", ["delete", "truncate", "grow"])
def test_damaged_output_invalidates_the_manifest(store: Store, key: str, damage: str) -> None:
    fp = _fingerprint()
    _commit(store, key, {"a.bin": os.urandom(4096), "b.bin": os.urandom(100)}, fp=fp)
    target = store.stage_dir(key, "reference") / "a.bin"
    if damage == "delete":
        target.unlink()
    elif damage == "truncate":
        target.write_bytes(target.read_bytes()[: secrets.randbelow(4096)])
    else:
        target.write_bytes(target.read_bytes() + b"x")
    assert store.read_manifest(key, "reference") is None
    assert store.lookup(key, "reference", fp) is None
    assert not store.verify(key, "reference")


def test_verify_catches_same_size_corruption(store: Store, key: str) -> None:
    _commit(store, key, {"a.bin": os.urandom(4096)})
    target = store.stage_dir(key, "reference") / "a.bin"
    data = bytearray(target.read_bytes())
    data[secrets.randbelow(len(data))] ^= 0xFF
    target.write_bytes(bytes(data))
    assert store.read_manifest(key, "reference") is not None  # the cheap check only looks at sizes
    assert not store.verify(key, "reference")


def test_unparseable_or_foreign_manifest_reads_as_missing(store: Store, key: str) -> None:
    _commit(store, key, {"a.bin": b"a"})
    path = store.stage_dir(key, "reference") / MANIFEST_FILE
    good = path.read_text()
    path.write_text(good[: len(good) // 2])
    assert store.read_manifest(key, "reference") is None
    path.write_text(good.replace('"schema": 1', '"schema": 2'))
    assert store.read_manifest(key, "reference") is None
    path.write_text(good.replace(f'"photo_key": "{key}"', '"photo_key": "other.jpg"'))
    assert store.read_manifest(key, "reference") is None


def test_non_finite_metrics_round_trip_as_strict_json(store: Store, key: str) -> None:
    manifest = _commit(store, key, {"a.bin": b"a"}, metrics={"psnr": float("inf"), "loss": [1.0, float("nan")],
                                                              "lpips": 0.1, "worst": -math.inf},
                       config={"max_lr": float("inf"), "name": "nan"}, notes=("first", "second"))
    text = (store.stage_dir(key, "reference") / MANIFEST_FILE).read_text()
    data = _strict(text)
    assert data["metrics"]["psnr"] == "inf" and data["metrics"]["worst"] == "-inf"
    assert data["config"]["max_lr"] == "inf"
    back = store.read_manifest(key, "reference")
    assert back is not None
    assert back.metrics["psnr"] == math.inf and back.metrics["worst"] == -math.inf
    assert math.isnan(back.metrics["loss"][1]) and back.metrics["lpips"] == 0.1
    assert back.notes == ("first", "second") and back.code_version == manifest.code_version
    assert back.config == {"max_lr": "inf", "name": "nan"}  # config strings are not reinterpreted
    assert _strict(back.to_json()) == data


@pytest.mark.parametrize(
    "mutate",
    [
        lambda d: d.pop("fingerprint"),
        lambda d: d.update(schema=99),
        lambda d: d.update(outputs={"../escape.bin": {"sha256": "0" * 64, "size": 1}}),
        lambda d: d.update(outputs={"/abs.bin": {"sha256": "0" * 64, "size": 1}}),
        lambda d: d.update(outputs={"a.bin": {"sha256": "zz", "size": 1}}),
        lambda d: d.update(outputs={"a.bin": {"sha256": "0" * 64, "size": -1}}),
        lambda d: d.update(notes="not a list"),
        lambda d: d.update(surprise=1),
        lambda d: d["fingerprint"].update(config_hash=3),
    ],
)
def test_from_json_rejects_malformed(mutate) -> None:
    data = json.loads(_manifest("mug.jpg").to_json())
    mutate(data)
    with pytest.raises(ValueError):
        Manifest.from_json(json.dumps(data))
    with pytest.raises(ValueError):
        Manifest.from_json('{"schema": 1, "stage": NaN}')


def _dead_pid() -> int:
    proc = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True,
                          check=True)
    return int(proc.stdout)


def test_cleanup_staging_removes_only_dead_writers(store: Store, key: str) -> None:
    _commit(store, key, {"a.bin": b"kept"})
    staging = store.staging_root(key)
    dead = [staging / f"reference.{_dead_pid()}.{secrets.token_hex(8)}",
            staging / f"geometry.999999999.{secrets.token_hex(8)}",
            staging / f"reference.{_dead_pid()}.{secrets.token_hex(8)}.old"]
    for folder in dead:
        (folder / "sub").mkdir(parents=True)
        (folder / "sub" / "half.bin").write_bytes(os.urandom(100))
    alive = staging / f"reference.{os.getpid()}.{secrets.token_hex(8)}"
    alive.mkdir()
    foreign = staging / "notes-by-a-human"
    foreign.mkdir()
    removed = store.cleanup_staging(key)
    assert sorted(removed) == sorted(dead)
    assert not any(p.exists() for p in dead)
    assert alive.is_dir() and foreign.is_dir()
    assert (store.stage_dir(key, "reference") / "a.bin").read_bytes() == b"kept"


def test_unsafe_keys_and_stage_names_are_rejected(store: Store, key: str) -> None:
    for bad_key in ["..", "../x", "a/b", ".hidden", ""]:
        with pytest.raises(UnsafeKeyError):
            store.stage_dir(bad_key, "reference")
        with pytest.raises(UnsafeKeyError):
            store.stage_writer(bad_key, "reference")
    for bad_stage in ["..", "Reference", "a/b", "a.b", "", ".staging", "x" * 65]:
        with pytest.raises(UnsafeKeyError):
            store.stage_dir(key, bad_stage)
        with pytest.raises(UnsafeKeyError):
            store.checkpoint_dir(key, bad_stage)
    assert not store.root.exists()  # nothing was created on the way


def test_symlinked_photo_folder_pointing_outside_is_caught(tmp_path: Path, key: str) -> None:
    store = Store(tmp_path / "store")
    outside = tmp_path / "outside"
    outside.mkdir()
    store.root.mkdir()
    (store.root / key).symlink_to(outside, target_is_directory=True)
    with pytest.raises(UnsafeKeyError, match="outside the store root"):
        store.stage_dir(key, "reference")
    with pytest.raises(UnsafeKeyError), store.stage_writer(key, "reference"):
        pass
    with pytest.raises(UnsafeKeyError):
        store.cleanup_staging(key)
    assert list(outside.iterdir()) == []


def test_symlinked_stage_folder_pointing_outside_is_caught(store: Store, key: str, tmp_path: Path) -> None:
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (store.root / key).mkdir(parents=True)
    (store.root / key / "reference").symlink_to(outside, target_is_directory=True)
    with pytest.raises(UnsafeKeyError):
        store.read_manifest(key, "reference")
    assert store.photo_dir(key) == store.root / key


def test_checkpoint_dir_and_clear(store: Store, key: str) -> None:
    folder = store.checkpoint_dir(key, "geometry")
    assert folder == store.root / key / ".checkpoints" / "geometry"
    folder.mkdir(parents=True)
    (folder / "step-000000001.ckpt").write_bytes(b"x")
    store.clear_checkpoints(key, "geometry")
    assert not folder.exists()
    store.clear_checkpoints(key, "geometry")  # idempotent


def test_keys_lists_only_safe_photo_folders(store: Store) -> None:
    names = sorted(f"p{secrets.token_hex(3)}.jpg" for _ in range(4))
    for name in names:
        (store.root / name).mkdir(parents=True)
    (store.root / ".hidden").mkdir()
    (store.root / "a b").mkdir()
    (store.root / "file.txt").write_text("not a folder")
    assert store.keys() == names
    assert Store(store.root / "missing").keys() == []


@dataclass(frozen=True)
class _Cfg:
    lr: float = 0.1
    steps: tuple[int, ...] = (1, 2)
    out: Path = Path("/tmp/x")
    extra: dict = field(default_factory=lambda: {"b": 1, "a": 2})


def test_config_hash_is_canonical_and_stable_across_processes(tmp_path: Path) -> None:
    cfg = _Cfg(lr=random.random())
    assert config_hash(cfg) == config_hash({"extra": {"a": 2, "b": 1}, "lr": cfg.lr, "out": "/tmp/x", "steps": [1, 2]})
    assert config_hash(cfg) != config_hash(replace(cfg, lr=cfg.lr + 1e-12))
    assert config_hash(cfg) != config_hash(replace(cfg, steps=(2, 1)))
    code = ("import sys; sys.path.insert(0, sys.argv[1]); from assets_store.hashing import config_hash; "
            "cfg = {'extra': {'b': 1, 'a': 2}, 'steps': (1, 2), 'out': '/tmp/x', 'lr': float(sys.argv[2])}; "
            "print(config_hash(cfg))")
    other = subprocess.run([sys.executable, "-c", code, str(Path(__file__).parent.parent), repr(cfg.lr)],
                           capture_output=True, text=True, check=True, env={**os.environ, "PYTHONHASHSEED": "random"})
    assert other.stdout.strip() == config_hash(cfg)
    assert '"lr":0.1' in canonical_json({"lr": 0.1}) and canonical_json({"x": math.inf}) == '{"x":"inf"}'


def test_file_sha256_streams_big_files(tmp_path: Path) -> None:
    data = os.urandom((1 << 20) * 2 + secrets.randbelow(1000))
    (tmp_path / "f.bin").write_bytes(data)
    assert file_sha256(tmp_path / "f.bin") == hashlib.sha256(data).hexdigest() == bytes_sha256(data)
