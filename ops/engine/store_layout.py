"""The store's layout version, and the migration of stores written before every stage had one id.

Layout 1 named three stage folders ``nerf_fit``, ``texture_refine`` and ``uv_bake``, keyed the
fingerprint inputs by those names and spelled two config groups ``dmtet.texture`` and
``bake.bake``. Layout 2 uses the stage ids (``nerf``, ``texture``, ``bake``) and the groups
``dmtet.texture_field`` and ``bake.map``. ``open_store`` migrates a layout-1 store in place, once,
so that every finished output is found again (cached, not re-run): per photo, each renamed
folder is moved (one atomic rename), and each manifest is rewritten (atomically) with the new
names and the config hash recomputed from its recorded config. Checkpoints of interrupted
stages move along: an interrupted NeRF or texture stage resumes where it was (its checkpoint folder
is named by its config and input hashes, which the renaming leaves alone); an interrupted DMTet
stage restarts from step 0, as its renamed config group changes its config hash.

The migration is idempotent and safe to interrupt (a re-run finishes it), and it runs under a
lock so concurrent processes opening the same store wait for one migration.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from assets_store.atomic import atomic_write_text
from assets_store.hashing import config_hash
from assets_store.keys import is_safe_key
from assets_store.manifest import MANIFEST_FILE, Manifest
from assets_store.store import CHECKPOINTS_DIR, Store
from ops.engine.stage_ids import RENAMED_STAGES, STAGE_IDS

log = logging.getLogger("morpheus3d")

LAYOUT = 2
LAYOUT_FILE = ".layout.json"
# Per stage: config paths renamed in layout 2 (old path → new path, inside the stage's hashed config).
RENAMED_CONFIG: dict[str, tuple[tuple[tuple[str, ...], tuple[str, ...]], ...]] = {
    "dmtet": ((("dmtet", "texture"), ("dmtet", "texture_field")),),
    "bake": ((("bake", "bake"), ("bake", "map")),),
}


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
    fd = os.open(store.root / ".layout.lock", os.O_RDWR | os.O_CREAT, 0o666)
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
        for stage in STAGE_IDS:
            try:
                if _migrate_manifest(store.stage_dir(key, stage) / MANIFEST_FILE, stage):
                    report.manifests_rewritten += 1
            except (OSError, ValueError, KeyError, TypeError) as exc:
                report.problems.append(f"{key}/{stage}: manifest not migrated ({exc})")
    return report


def _rename_path(config: dict[str, Any], old: tuple[str, ...], new: tuple[str, ...]) -> bool:
    parent = config
    for part in old[:-1]:
        parent = parent.get(part) if isinstance(parent, dict) else None
        if parent is None:
            return False
    if not isinstance(parent, dict) or old[-1] not in parent or new[-1] in parent:
        return False
    parent[new[-1]] = parent.pop(old[-1])
    return True


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
    renamed = [_rename_path(config, old, new) for old, new in RENAMED_CONFIG.get(stage, ())]
    if any(renamed) and reproducible:
        fp["config_hash"] = config_hash(config)
        changed = True
    if changed:
        text = Manifest.from_json(json.dumps(data)).to_json()  # validates before it replaces the old one
        atomic_write_text(path, text)
    return changed
