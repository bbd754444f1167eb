"""One id per stage: the declarations in ``ops.stages`` are what the pipeline, the config, the store,
the Dagster assets and the QA checks use; old keys still work; every setting says what it does."""

from __future__ import annotations

import dataclasses
import importlib
import logging

import dagster as dg
import pytest

from ops.cli import main
from ops.config.presets import PipelineConfig, preset
from ops.engine.config_tree import ConfigError, describe_keys
from ops.migrations import RENAMED_ASSETS, RENAMED_STAGES, current_stage_id
from ops.stages import BY_ID, CHECKS, STAGE_IDS, STAGES
from orchestration.definitions import build_definitions


def test_one_id_names_module_config_key_and_asset() -> None:
    fields = {f.name for f in dataclasses.fields(PipelineConfig)}
    assert tuple(s.id for s in STAGES) == STAGE_IDS
    for stage in STAGES:
        assert importlib.import_module(f"ops.stages.{stage.id}").STAGE is stage
        assert stage.id in fields, f"cfg.{stage.id} holds the {stage.id} stage's settings"
        assert stage.preview in stage.writes
        assert all(STAGE_IDS.index(r) < STAGE_IDS.index(stage.id) for r in stage.reads), "reads come earlier"
    assert set(CHECKS) == set(STAGE_IDS)
    graph = build_definitions().resolve_asset_graph()
    for stage in STAGES:
        node = graph.get(dg.AssetKey(stage.id))
        assert node.code_version == stage.code_version
        assert node.parent_keys == {dg.AssetKey(r) for r in (stage.reads or ("photo_files",))}


def test_old_names_map_to_the_current_ids() -> None:
    assert set(RENAMED_STAGES.values()) <= set(STAGE_IDS) and not set(RENAMED_STAGES) & set(STAGE_IDS)
    assert {current_stage_id(s) for s in ("nerf_fit", "texture_refine", "uv_bake", "dmtet")} == {
        "nerf", "texture", "bake", "dmtet"}
    assert set(RENAMED_ASSETS.values()) <= set(STAGE_IDS)


def test_keys_from_before_the_renaming_still_work(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, logger="morpheus3d"):
        old = preset("draft", ["prepare.segment.min_confidence=0.3", "bake.bake.texture_size=128",
                               "dmtet.texture.hidden_dim=16", "plan.hf_threshold=0.2"])
    assert old.reference.prepare.segment.min_confidence == 0.3 and old.bake.map.texture_size == 128
    assert old.dmtet.texture_field.hidden_dim == 16 and old.reference.plan.hf_threshold == 0.2
    assert "reference.prepare.segment.min_confidence" in caplog.text and "bake.map.texture_size" in caplog.text
    with pytest.raises(ConfigError, match="texture_sise"):
        preset("draft", ["bake.bake.texture_sise=128"])


def test_every_setting_has_a_one_line_doc() -> None:
    missing = [key for key, _, doc in describe_keys(preset("paper")) if not doc]
    assert not missing, f"settings without a doc line (an attribute docstring after the field): {missing}"


def test_list_keys_prints_key_default_and_doc(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", "examples/photos/mug.jpg", "--out", "unused", "--list-keys"]) == 0
    lines = {line.split()[0]: line for line in capsys.readouterr().out.splitlines()}
    assert len(lines) == len(describe_keys(preset("draft")))
    line = lines["nerf.loop.steps"]
    assert line.split()[1] == "150" and len(line.split()) > 3, line


def test_until_accepts_an_old_stage_name(tmp_path, capsys) -> None:
    assert main(["run", "no-such-photo.jpg", "--out", str(tmp_path), "--until", "uv_bake"]) == 2
    assert "no such file" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["run", "no-such-photo.jpg", "--out", str(tmp_path), "--until", "nerf_fitt"])


def test_stage_of_unknown_id_is_refused() -> None:
    assert BY_ID["bake"].gpu is False and BY_ID["nerf"].replaced_by_init_mesh
    from ops.pipeline.runner import check_stage_id
    with pytest.raises(ValueError, match="must be one of"):
        check_stage_id("uv_bakes")
