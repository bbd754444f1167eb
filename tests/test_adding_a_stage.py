"""Adding a stage is one module and one line (README, "Adding a stage"): a toy stage, declared in a module
of its own and named once in ``ops.stages.STAGE_IDS``, gets its config section (``--set``, ``--list-keys``),
runs through the command line with caching by fingerprint, declares its QA check and becomes a Dagster asset,
with no other file touched. It runs in a fresh interpreter: the declarations are read once per process."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
from PIL import Image

from tests.pipeline_helpers import PHOTOS

TOY_MODULE = '''
"""A toy stage: the share of the reference mask above a threshold."""
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from ops.engine.checks import WARN, CheckSpec, check
from ops.engine.stage import Stage, StageWork
from ops.engine.stage_job import StageResult


@dataclass(frozen=True)
class ToyConfig:
    threshold: float = 0.5
    """Mask value (0-1) above which a pixel counts."""


COVERED = CheckSpec("covered", WARN, "some of the mask is above the threshold")


def _build(ctx, cfg):
    def body(out: Path, _ckpt):
        mask = max(ctx.dir("reference").glob("mask_*.png"), key=lambda p: p.stat().st_size)
        share = float((np.asarray(Image.open(mask).convert("L")) / 255.0 > cfg.threshold).mean())
        (out / "toy.json").write_text(f'{{"mask": "{mask.name}", "share": {share}}}')
        return StageResult({"share": share}, "none", "cpu")
    return StageWork({"threshold": cfg.threshold}, body, inputs={"photo": ctx.photo_hash()})


STAGE = Stage("toy", "toy-1", config=ToyConfig, reads=("reference",), writes=("toy.json",), preview="toy.json",
              gpu=False, cpu_only=True, build=_build, description="A toy stage.", checks=(COVERED,),
              judge=lambda m, _t: [check(COVERED, m["share"] > 0, m["share"], 0, "mask share")])
'''

DRIVER = '''
import contextlib, io, json, sys
from pathlib import Path

import ops.stages
ops.stages.__path__.append(sys.argv[1])  # where the new module lies (in the product: ops/stages/toy.py)
ops.stages.STAGE_IDS = ("reference", "toy") + ops.stages.STAGE_IDS[1:]  # the one line

import dagster as dg
from assets_store.store import Store
from ops.cli import main
from ops.config.presets import preset
from ops.engine.config_tree import describe_keys
from ops.stages import CHECKS, stage_checks
from orchestration.definitions import build_definitions

photo, store_dir = sys.argv[2], Path(sys.argv[3])
keys = {k: v for k, v, _ in describe_keys(preset("draft", ["toy.threshold=0.25"]))}
with contextlib.redirect_stdout(io.StringIO()):
    first = main(["run", photo, "--out", str(store_dir), "--until", "toy", "--set", "toy.threshold=0.25"])
store = Store(store_dir)
before = {s: store.read_manifest("mug.jpg", s) for s in ("reference", "toy")}
with contextlib.redirect_stdout(io.StringIO()):
    second = main(["run", photo, "--out", str(store_dir), "--until", "toy", "--set", "toy.threshold=0.75"])
after = {s: store.read_manifest("mug.jpg", s) for s in ("reference", "toy")}
graph = build_definitions().resolve_asset_graph()
print(json.dumps({
    "exit": [first, second], "key": keys.get("toy.threshold"),
    "reference_cached": before["reference"].created_at == after["reference"].created_at
                        and before["reference"].fingerprint == after["reference"].fingerprint,
    "toy_reran": before["toy"].fingerprint != after["toy"].fingerprint,
    "config": [before["toy"].config, after["toy"].config], "share": [before["toy"].metrics["share"],
                                                                     after["toy"].metrics["share"]],
    "checks": [c.name for c in CHECKS["toy"]],
    "judged": [c.passed for c in stage_checks("toy", after["toy"].metrics, preset("draft").qa)],
    "asset_parents": sorted(k.to_user_string() for k in graph.get(dg.AssetKey("toy")).parent_keys),
}))
'''


def test_a_new_stage_is_one_module_and_one_line(tmp_path: Path) -> None:
    (tmp_path / "stages").mkdir()
    (tmp_path / "stages" / "toy.py").write_text(textwrap.dedent(TOY_MODULE))
    done = subprocess.run([sys.executable, "-c", DRIVER, str(tmp_path / "stages"), str(PHOTOS / "mug.jpg"),
                           str(tmp_path / "store")], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["exit"] == [0, 0] and out["key"] == 0.25  # its config section, overridable like any other
    assert out["reference_cached"] and out["toy_reran"]  # its fingerprint holds its config, nothing else changed
    assert [c["threshold"] for c in out["config"]] == [0.25, 0.75]
    mask = tmp_path / "store" / "mug.jpg" / "reference"
    values = np.asarray(Image.open(max(mask.glob("mask_*.png"), key=lambda p: p.stat().st_size)).convert("L")) / 255
    assert out["share"] == [float((values > 0.25).mean()), float((values > 0.75).mean())]
    assert out["checks"] == ["covered"] and out["judged"] == [True]
    assert out["asset_parents"] == ["reference"]
