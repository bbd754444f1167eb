"""Execution settings (``morpheus_core.runtime.execution``): from their environment aliases and from
``--set``, applied process-wide when a run starts, refused with the key's name when bad, and in
no stage's fingerprint (changing them keeps every cached output)."""

from __future__ import annotations

from pathlib import Path

import pytest

from assets_store.hashing import config_hash
from assets_store.manifest import Fingerprint
from morpheus_core.runtime.execution import ExecutionConfig, apply_execution, current_execution, executing
from ops.cli import main
from ops.config.presets import PipelineConfig, preset
from ops.engine.config_tree import ConfigError
from ops.intake.plan import StagePlan
from ops.pipeline.photo_run import stage_config_record
from ops.pipeline.runner import run_setup
from ops.stages import STAGE_IDS, STAGES
from tests.pipeline_helpers import PHOTOS


def test_environment_aliases_give_the_defaults() -> None:
    assert ExecutionConfig.from_env({}) == ExecutionConfig("auto", "auto", True)
    env = {"MORPHEUS_HASHGRID": "eager", "MORPHEUS_FIELD_MLP": "Triton", "MORPHEUS_COMPILE": "0"}
    assert ExecutionConfig.from_env(env) == ExecutionConfig(hashgrid="eager", field_mlp="triton", compile=False)
    assert ExecutionConfig.from_env({"MORPHEUS_HASHGRID": "", "MORPHEUS_COMPILE": "1"}) == ExecutionConfig()
    with pytest.raises(ValueError, match=r"MORPHEUS_HASHGRID \(execution\.hashgrid\) must be one of auto, triton"):
        ExecutionConfig.from_env({"MORPHEUS_HASHGRID": "fast"})
    with pytest.raises(ValueError, match=r"MORPHEUS_COMPILE \(execution\.compile\) must be 0 or 1"):
        ExecutionConfig.from_env({"MORPHEUS_COMPILE": "sometimes"})


def test_a_preset_takes_its_execution_defaults_from_the_aliases(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MORPHEUS_HASHGRID", "eager")
    monkeypatch.setenv("MORPHEUS_COMPILE", "0")
    cfg = preset("draft")
    assert cfg.execution == ExecutionConfig(hashgrid="eager", compile=False)
    assert preset("draft", ["execution.hashgrid=triton"]).execution.hashgrid == "triton"  # --set wins
    monkeypatch.setenv("MORPHEUS_FIELD_MLP", "fused")
    with pytest.raises(ConfigError, match=r"MORPHEUS_FIELD_MLP \(execution\.field_mlp\)"):
        preset("draft")
    assert main(["run", "--list-keys"]) == 2  # the CLI says so before any work


def test_set_and_list_keys(capsys: pytest.CaptureFixture[str]) -> None:
    cfg = preset("draft", ["execution.hashgrid=triton", "execution.field_mlp=eager", "execution.compile=false"])
    assert cfg.execution == ExecutionConfig(hashgrid="triton", field_mlp="eager", compile=False)
    with pytest.raises(ConfigError, match=r"execution\.hashgrid: 'fast' is not one of"):
        preset("draft", ["execution.hashgrid=fast"])
    with pytest.raises(ConfigError, match=r"execution\.compile: expected true/false"):
        preset("draft", ["execution.compile=sometimes"])
    with pytest.raises(ValueError, match=r"execution\.field_mlp must be one of auto, triton, eager; got 'fast'"):
        ExecutionConfig(hashgrid="triton", field_mlp="fast")  # type: ignore[arg-type]
    assert main(["run", "--list-keys", "--set", "execution.hashgrid=triton"]) == 0
    lines = {line.split()[0]: line for line in capsys.readouterr().out.splitlines()}
    assert {"execution.hashgrid", "execution.field_mlp", "execution.compile"} <= set(lines)
    assert lines["execution.hashgrid"].split()[1] == '"triton"' and "MORPHEUS_HASHGRID" in lines["execution.hashgrid"]
    assert main(["run", "--list-keys", "--set", "execution.field_mlp=fast"]) == 2
    assert "execution.field_mlp" in capsys.readouterr().err


def test_a_run_applies_its_execution_settings_and_restores_them(monkeypatch: pytest.MonkeyPatch) -> None:
    before = current_execution()
    cfg = preset("draft", ["device=cpu", "execution.hashgrid=eager", "execution.compile=false"])
    monkeypatch.setenv("MORPHEUS_HASHGRID", "triton")  # read for defaults only: the applied config wins
    with run_setup(cfg) as (leased, lease):
        assert current_execution() == cfg.execution and leased.device == "cpu" and lease is None
    assert current_execution() == before
    previous = apply_execution(ExecutionConfig(field_mlp="eager"))
    try:
        assert previous == before and current_execution().field_mlp == "eager"
    finally:
        apply_execution(previous)
    with executing(ExecutionConfig(hashgrid="triton")):
        assert current_execution().hashgrid == "triton"
    assert current_execution() == before


class _Declaring:
    """A ``StageContext`` that declares every stage's work without a store: no plan yet, proxy priors."""

    key = "mug.jpg"
    photo = PHOTOS / "mug.jpg"
    init_mesh = None
    plan: StagePlan | None = None
    stages = STAGE_IDS

    def __init__(self, cfg: PipelineConfig) -> None:
        self.seed, self.device, self.priors = cfg.seed, cfg.device, cfg.priors

    def dir(self, stage: str) -> Path:
        return Path("unused") / stage

    def upstream(self, stage: str) -> None:
        raise AssertionError("declaring a stage's work reads no upstream output")

    def photo_hash(self) -> str:
        return "photo"

    def prior_kind(self, roles: tuple[str, ...]) -> str:
        return "proxy"

    def suite(self, stage: str) -> None:
        return None

    def progress(self) -> None:
        return None


def fingerprints(cfg: PipelineConfig) -> dict[str, Fingerprint]:
    """Each stage's fingerprint for ``cfg``, hashed as ``PhotoRun.planned`` hashes it (same upstream outputs)."""
    ctx = _Declaring(cfg)
    out = {}
    for stage in STAGES:
        work = stage.build(ctx, getattr(cfg, stage.id))
        out[stage.id] = Fingerprint(work.inputs, config_hash(stage_config_record(work.config)), stage.code_version)
    return out


def test_execution_settings_are_in_no_stage_fingerprint(monkeypatch: pytest.MonkeyPatch) -> None:
    base = fingerprints(preset("draft"))
    assert set(base) == set(STAGE_IDS)
    for change in (["execution.hashgrid=eager"], ["execution.field_mlp=triton", "execution.compile=false"],
                   ["execution.hashgrid=triton", "execution.field_mlp=eager"]):
        assert fingerprints(preset("draft", change)) == base, change
    monkeypatch.setenv("MORPHEUS_COMPILE", "0")  # through the alias as well
    assert fingerprints(preset("draft")) == base
    # A real setting changes its stage's fingerprint (downstream ones follow through their inputs).
    steps = fingerprints(preset("draft", ["nerf.loop.steps=151"]))
    assert steps["nerf"] != base["nerf"] and steps["reference"] == base["reference"]
    # The sample gather stays a NeRF setting: padded buffers can drop samples (not rounding only).
    padded = fingerprints(preset("draft", ["nerf.render.sample_buffer=padded"]))
    assert padded["nerf"] != base["nerf"] and padded["dmtet"] == base["dmtet"]
