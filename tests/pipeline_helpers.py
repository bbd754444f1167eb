"""A tiny pipeline configuration for CPU tests (the draft preset, shrunk further) and store readers."""

from __future__ import annotations

import os
from pathlib import Path

from assets_store.manifest import Manifest
from assets_store.store import Store
from ops.config.presets import PipelineConfig, preset, with_steps

ROOT = Path(__file__).resolve().parent.parent
PHOTOS = ROOT / "examples" / "photos"

# Small enough that one photo runs every stage in ~7 s on two cores, with checkpoints every 2 steps. The NeRF
# preview at 32 px: at its default 128 px its four volume renders cost twice the tiny NeRF fit itself.
DEVICE = os.environ.get("MORPHEUS_TEST_DEVICE", "cpu")  # the GPU session runs these on CUDA too
TINY_OVERRIDES = [
    f"device={DEVICE}", "priors.kind=proxy", "priors.proxy_grid=24",
    "nerf.resolution=24", "nerf.render.n_samples=24", "nerf.occupancy.resolution=16", "nerf.preview_size=32",
    "dmtet.resolution=40", "dmtet.max_grid=24", "dmtet.colour_fit_steps=40", "dmtet.colour_fit_points=2048",
    "dmtet.conversion.ring_views=3", "dmtet.conversion.resolution=32", "dmtet.conversion.samples=24",
    "texture.resolution=40", "texture.follow_plan=false",
    "bake.map.texture_size=64", "bake.eval_resolution=64", "bake.turntable_views=4",
    "qa.eval_resolution=64", "qa.turntable_views=4", "qa.turntable_resolution=64",
    "qa.part_resolution=32", "qa.part_samples=24",
]


def tiny_config(*overrides: str, nerf: int = 8, dmtet: int = 6, texture: int = 6) -> PipelineConfig:
    return with_steps(preset("draft", [*TINY_OVERRIDES, *overrides]), nerf, dmtet, texture)


def cli_overrides(cfg: PipelineConfig) -> list[str]:
    """The same tiny configuration as ``--set`` arguments for a subprocess."""
    args = []
    for item in TINY_OVERRIDES:
        args += ["--set", item]
    for stage in ("nerf", "dmtet", "texture"):
        loop = getattr(cfg, stage).loop
        args += ["--set", f"{stage}.loop.steps={loop.steps}", "--set", f"{stage}.loop.checkpoint_every="
                 f"{loop.checkpoint_every}", "--set", f"{stage}.loop.log_every={loop.log_every}"]
    grid = cfg.nerf.model.grid
    args += ["--set", f"nerf.model.grid.start_step={grid.start_step}",
             "--set", f"nerf.model.grid.update_steps={grid.update_steps}"]
    return args


def output_hashes(store: Store, key: str, stage: str) -> dict[str, str]:
    """Content hashes of a finished stage's outputs, except the run log (it records wall time)."""
    manifest = store.read_manifest(key, stage)
    assert manifest is not None, f"{stage} has no finished output"
    return {name: rec.sha256 for name, rec in manifest.outputs.items() if name != "runlog.parquet"}


def manifest(store: Store, key: str, stage: str) -> Manifest:
    m = store.read_manifest(key, stage)
    assert m is not None, f"{stage} has no finished output"
    return m
