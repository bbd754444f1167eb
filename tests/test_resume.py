"""Kill and resume: a `morpheus3d run` killed with SIGKILL at a random point of each stage, then
restarted, finishes with outputs bit-identical to an uninterrupted run (CPU, same seed)."""

from __future__ import annotations

import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from assets_store.store import Store
from tests.pipeline_helpers import PHOTOS, ROOT, cli_overrides, output_hashes, tiny_config

KEY = "mug.jpg"
# More steps than the other pipeline tests, so that each stage spends long enough to be hit.
CFG = tiny_config(nerf=16, dmtet=12, texture=12)
UPSTREAM = {"nerf": ("reference",), "dmtet": ("reference", "nerf"),
            "texture": ("reference", "nerf", "dmtet"),
            "bake": ("reference", "nerf", "dmtet", "texture")}


def _command(out: Path) -> list[str]:
    return [sys.executable, "-m", "ops.cli", "run", str(PHOTOS / "mug.jpg"), "--out", str(out), "--preset", "draft",
            *cli_overrides(CFG)]


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(ROOT)}


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory: pytest.TempPathFactory) -> Store:
    out = tmp_path_factory.mktemp("full")
    subprocess.run(_command(out), env=_env(), check=True, capture_output=True, timeout=600)
    return Store(out)


def _reached(store: Store, stage: str, step: int) -> bool:
    """The stage has checkpointed ``step`` or later, or (bake, no steps) opened its staging folder."""
    if stage == "bake":
        return store.staging_root(KEY).exists() and any(store.staging_root(KEY).glob("bake.*"))
    return any(int(p.stem.split("-")[1]) >= step for p in store.checkpoint_dir(KEY, stage).glob("**/step-*.ckpt"))


@pytest.mark.parametrize("stage", ["nerf", "dmtet", "texture", "bake"])
def test_sigkill_at_a_random_step_then_resume_is_bit_identical(stage: str, uninterrupted: Store,
                                                                tmp_path: Path) -> None:
    store = Store(tmp_path / "store")
    for done in UPSTREAM[stage]:  # finished upstream stages are cache hits, so the kill lands in `stage`
        shutil.copytree(uninterrupted.stage_dir(KEY, done), store.stage_dir(KEY, done))
    rng = random.Random(f"{stage}-{os.getpid()}")
    proc = subprocess.Popen(_command(store.root), env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    # A random checkpoint (first to third of four, before the step the stage stops at when its
    # scene converges early), then a random moment up to a few steps later.
    loop = {"nerf": CFG.nerf.loop, "dmtet": CFG.dmtet.loop, "texture": CFG.texture.loop}.get(stage)
    step = 0
    if loop:
        metrics = uninterrupted.read_manifest(KEY, stage).metrics
        reached = metrics["schedule_steps"] - metrics["steps_saved"]
        step = rng.randint(1, max(1, min(3, (reached - 1) // loop.checkpoint_every))) * loop.checkpoint_every
    deadline = time.monotonic() + 300
    while not _reached(store, stage, step) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.002)
    time.sleep(rng.uniform(0.0, 0.05))
    killed = proc.poll() is None
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert killed, f"the run finished before it could be killed in {stage}; make the stage longer"
    assert store.read_manifest(KEY, stage) is None or stage == "bake"

    subprocess.run(_command(store.root), env=_env(), check=True, capture_output=True, timeout=600)
    for s in ("nerf", "dmtet", "texture", "bake"):
        assert output_hashes(store, KEY, s) == output_hashes(uninterrupted, KEY, s), s
    if stage != "bake":
        resumed = store.read_manifest(KEY, stage).metrics["resumed_from_step"]
        assert resumed is None or resumed > 0
    staging = store.staging_root(KEY)
    assert not staging.exists() or not any(staging.iterdir())  # the dead run's staging folder is gone
