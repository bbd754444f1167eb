"""The store's layout version, and the migration of stores written before every stage had one id.

Layout 1 named three stage folders ``nerf_fit``, ``texture_refine`` and ``uv_bake``, keyed the
fingerprint inputs by those names, spelled two config groups ``dmtet.texture`` and ``bake.bake``
and held the LoRA settings as ``priors.lora_rank`` / ``priors.lora_lr``. Layout 2 uses the stage
ids (``nerf``, ``texture``, ``bake``), the groups ``dmtet.texture_field`` and ``bake.map`` and one
``priors.lora`` group (``LoraSettings``). ``open_store`` migrates a layout-1 store in place, once, so
that every finished output is found again (cached, not re-run): per photo, each renamed folder is
moved (one atomic rename), and each manifest is rewritten (atomically) with the new names and the
config hash recomputed from its recorded config. Checkpoints of interrupted stages move with their
stage folder; as their folder names hash the config and the inputs' names, the pipeline looks for
a stage's layout-1 checkpoint folder before it starts (``adopt_layout1_checkpoint``), so an
interrupted stage resumes where it was.

The migration is idempotent and safe to interrupt (a re-run finishes it), and it runs under a
lock so concurrent processes opening the same store wait for one migration.
"""

from __future__ import annotations

import copy
import fcntl
import json
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from assets_store.atomic import atomic_write_text
from assets_store.hashing import bytes_sha256, config_hash
from assets_store.keys import is_safe_key
from assets_store.manifest import MANIFEST_FILE, Fingerprint, Manifest
from assets_store.store import CHECKPOINTS_DIR, Store
from ops.migrations import RENAMED_STAGES

log = logging.getLogger("morpheus3d")

LAYOUT = 2
LAYOUT_FILE = ".layout.json"
LAYOUT_LOCK = ".layout.lock"
OLD_IDS = {new: old for old, new in RENAMED_STAGES.items()}
# What layout 1 ran its LoRA with besides rank and learning rate (``LoraSettings``' defaults then).
LAYOUT1_LORA = {"alpha": 4.0, "target_modules": ["to_q", "to_k", "to_v", "to_out.0"], "betas": [0.9, 0.999]}


@dataclass(frozen=True)
class ConfigChange:
    """One change of the stages' hashed configs from layout 1 to 2, both ways: ``forward`` migrates a
    recorded config, ``backward`` finds where an interrupted stage left its checkpoints. Each edits
    the JSON config in place and says whether it changed anything."""

    stages: tuple[str, ...]
    forward: Callable[[dict[str, Any]], bool]
    backward: Callable[[dict[str, Any]], bool]


def _group(config: dict[str, Any], path: tuple[str, ...]) -> dict[str, Any] | None:
    for part in path:
        config = config.get(part) if isinstance(config, dict) else None  # type: ignore[assignment]
    return config if isinstance(config, dict) else None


def _move(config: dict[str, Any], old: tuple[str, ...], new: tuple[str, ...]) -> bool:
    parent = _group(config, old[:-1])
    if parent is None or old[-1] not in parent or new[-1] in parent:
        return False
    parent[new[-1]] = parent.pop(old[-1])
    return True


def renamed(old: tuple[str, ...], new: tuple[str, ...], *stages: str) -> ConfigChange:
    return ConfigChange(stages, lambda c: _move(c, old, new), lambda c: _move(c, new, old))


def _lora_forward(config: dict[str, Any]) -> bool:
    priors = _group(config, ("priors",))
    if priors is None or "lora_rank" not in priors:
        return False
    priors["lora"] = {"rank": priors.pop("lora_rank"), "lr": priors.pop("lora_lr"), **LAYOUT1_LORA}
    return True


def _lora_backward(config: dict[str, Any]) -> bool:
    lora = _group(config, ("priors", "lora"))
    if lora is None or any(lora.get(k) != v for k, v in LAYOUT1_LORA.items()):
        return False  # settings layout 1 could not express: no layout-1 checkpoint can exist
    priors = config["priors"]
    del priors["lora"]
    priors["lora_rank"], priors["lora_lr"] = lora["rank"], lora["lr"]
    return True


# In order; ``backward`` runs them in reverse.
CONFIG_CHANGES = (
    renamed(("dmtet", "texture"), ("dmtet", "texture_field"), "dmtet"),
    renamed(("bake", "bake"), ("bake", "map"), "bake"),
    ConfigChange(("nerf", "dmtet", "texture"), _lora_forward, _lora_backward),
)


@dataclass
class Migration:
    """What a migration did (empty when the store was already current)."""

    photos: int = 0
    folders_renamed: int = 0
    manifests_rewritten: int = 0
    checkpoints_moved: int = 0
    problems: list[str] = field(default_factory=list)

    def summary(self) -> str:
        return (f"store layout {LAYOUT}: {self.folders_renamed} stage folders renamed, {self.manifests_rewritten} "
                f"manifests rewritten, {self.checkpoints_moved} checkpoint folders moved, over {self.photos} photos"
                + (f"; {len(self.problems)} problems: " + "; ".join(self.problems) if self.problems else ""))


def layout_of(root: Path) -> int:
    """The layout a store was written with: 1 when it predates the layout file, 2 for a new store."""
    marker = Path(root) / LAYOUT_FILE
    if marker.is_file():
        return int(json.loads(marker.read_text(encoding="utf-8"))["layout"])
    has_photos = Path(root).is_dir() and any(p.is_dir() and is_safe_key(p.name) for p in Path(root).iterdir())
    return 1 if has_photos else LAYOUT


def open_store(root: Path | str) -> Store:
    """The store at ``root``, migrated to the current layout first when it is older."""
    store = Store(root)
    if store.root.is_dir() and layout_of(store.root) == LAYOUT and (store.root / LAYOUT_FILE).is_file():
        return store
    store.root.mkdir(parents=True, exist_ok=True)
    fd = os.open(store.root / LAYOUT_LOCK, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)  # another process migrating: wait for it, then find it done
        if layout_of(store.root) < LAYOUT:
            report = migrate(store)
            log.warning("%s: %s", store.root, report.summary())
        atomic_write_text(store.root / LAYOUT_FILE, json.dumps({"layout": LAYOUT}) + "\n")
    finally:
        os.close(fd)
    return store


def migrate(store: Store) -> Migration:
    """Move every photo of a layout-1 store to layout 2 (see the module docstring)."""
    report = Migration()
    for key in store.keys():
        report.photos += 1
        photo = store.photo_dir(key)
        for old, new in RENAMED_STAGES.items():
            for parent in (photo, photo / CHECKPOINTS_DIR):
                src, dst = parent / old, parent / new
                if src.is_dir() and not dst.exists():
                    os.replace(src, dst)
                    report.folders_renamed += parent == photo
                    report.checkpoints_moved += parent != photo
                elif src.is_dir():
                    report.problems.append(f"{key}: both {src.name}/ and {dst.name}/ exist; kept {dst.name}/")
        # Every stage folder with a manifest (this layer does not know the stage list; old names were renamed above).
        stages = sorted(p.name for p in photo.iterdir()
                        if (p / MANIFEST_FILE).is_file() and p.name not in RENAMED_STAGES)
        for stage in stages:
            try:
                if _migrate_manifest(store.stage_dir(key, stage) / MANIFEST_FILE, stage):
                    report.manifests_rewritten += 1
            except (OSError, ValueError, KeyError, TypeError) as exc:
                report.problems.append(f"{key}/{stage}: manifest not migrated ({exc})")
    return report


def _migrate_manifest(path: Path, stage: str) -> bool:
    """Rewrite one manifest with layout-2 names; False when it is missing or already current."""
    if not path.is_file():
        return False
    data = json.loads(path.read_text(encoding="utf-8"))
    fp = data["fingerprint"]
    changed = data["stage"] != stage
    data["stage"] = stage
    inputs = {RENAMED_STAGES.get(k, k): v for k, v in fp["inputs"].items()}
    changed |= inputs != fp["inputs"]
    fp["inputs"] = inputs
    config = data.get("config", {})
    # Only a recorded config that reproduces the recorded hash can be re-hashed; any other stays
    # as it is (its stage then re-runs, which is safe).
    reproducible = config_hash(config) == fp["config_hash"]
    changes = [change.forward(config) for change in CONFIG_CHANGES if stage in change.stages]
    if any(changes) and reproducible:
        fp["config_hash"] = config_hash(config)
        changed = True
    if changed:
        text = Manifest.from_json(json.dumps(data)).to_json()  # validates before it replaces the old one
        atomic_write_text(path, text)
    return changed


def checkpoint_path(store: Store, key: str, stage: str, fp: Fingerprint) -> Path:
    """Where a stage resumes from: one folder per (config, inputs), so a changed input starts afresh."""
    root = store.checkpoint_dir(key, stage)
    return root / fp.config_hash[:12] / bytes_sha256(repr(sorted(fp.inputs.items())).encode())[:12]


def adopt_layout1_checkpoint(store: Store, key: str, stage: str, config: dict[str, Any], fp: Fingerprint) -> bool:
    """Move the checkpoints a layout-1 run of this stage (same settings and inputs) left under its
    layout-1 folder name to where the stage resumes now; False when there are none."""
    target = checkpoint_path(store, key, stage, fp)
    if target.exists():
        return False
    old_config = copy.deepcopy(config)
    for change in reversed(CONFIG_CHANGES):
        if stage in change.stages:
            change.backward(old_config)
    old_inputs = {OLD_IDS.get(k, k): v for k, v in fp.inputs.items()}
    legacy = checkpoint_path(store, key, stage, Fingerprint(old_inputs, config_hash(old_config), fp.code_version))
    if legacy == target or not legacy.is_dir():
        return False
    target.parent.mkdir(parents=True, exist_ok=True)
    os.replace(legacy, target)
    log.info("%s: %s resumes from the checkpoints of a run from before the store layout %d", key, stage, LAYOUT)
    return True
