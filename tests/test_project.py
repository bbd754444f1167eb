"""Installation, command line, layout and dependency direction."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from morpheus_core.priors.registry import ModelRegistry
from ops.cli import cv2_status, main

ROOT = Path(__file__).resolve().parent.parent


def test_opencv_is_the_contrib_build() -> None:
    import cv2

    assert hasattr(cv2, "ximgproc") and callable(cv2.ximgproc.guidedFilter)  # contrib-only symbol
    assert cv2.__version__.split(".")[0] == "4"
    assert cv2_status()[0]


def test_version_flag(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.startswith("morpheus3d ")


def test_doctor_reports_packages_cuda_cv2_and_models(tmp_path: Path, monkeypatch, capsys) -> None:
    monkeypatch.setenv("MORPHEUS_MODELS", str(tmp_path))
    controlnet = tmp_path / "controlnet-canny"
    controlnet.mkdir()
    (controlnet / "config.json").write_text("{}")
    (controlnet / "diffusion_pytorch_model.safetensors").write_bytes(b"x")
    assert main(["doctor"]) == 0
    out = capsys.readouterr().out
    assert "CUDA available:" in out and "contrib modules present" in out
    assert f"root {tmp_path}, from $MORPHEUS_MODELS" in out
    assert "controlnet_canny   present" in out
    assert "zero123            missing" in out and "expected file: unet/config.json" in out
    assert "3d prior weights missing" in out and "2d prior weights missing" in out
    monkeypatch.setenv("MORPHEUS_GPUS", "0,1")
    monkeypatch.setenv("MORPHEUS_GPU_SLOTS", "3")
    assert main(["doctor"]) == 0 and "GPU leases: 2 GPU(s) × 3 run(s) each" in capsys.readouterr().out
    monkeypatch.setenv("MORPHEUS_GPU_SLOTS", "lots")
    assert main(["doctor"]) == 1 and "GPU leases: bad setting: MORPHEUS_GPU_SLOTS='lots'" in capsys.readouterr().out


def test_model_check_names_missing_files(tmp_path: Path) -> None:
    status = ModelRegistry(root=tmp_path).status("zero123")
    assert not status.present and status.path == tmp_path / "zero123-xl"
    assert "cc_projection/config.json or clip_camera_projection/config.json" in status.missing


def test_console_script_is_installed() -> None:
    exe = Path(sys.executable).parent / "morpheus3d"
    res = subprocess.run([str(exe), "--version"], capture_output=True, text=True, check=True)
    assert res.stdout.startswith("morpheus3d ")


def test_layout_matches_design() -> None:
    for path in ["pyproject.toml", "workspace.yaml", "README.md", "Makefile", ".ci/run", "morpheus_core",
                 "ops", "assets_store", "orchestration", "tests", "benchmarks"]:
        assert (ROOT / path).exists(), path


def test_workspace_code_location_loads() -> None:
    import yaml
    from dagster import Definitions

    spec = yaml.safe_load((ROOT / "workspace.yaml").read_text())["load_from"][0]["python_module"]
    module = __import__(spec["module_name"], fromlist=["defs"])
    assert isinstance(module.defs, Definitions)


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module.split(".")[0])
    return names


@pytest.mark.parametrize(
    "package,forbidden",
    [("morpheus_core", {"dagster", "orchestration", "ops", "assets_store"}),
     ("ops", {"dagster", "orchestration"}),
     ("assets_store", {"dagster", "orchestration", "ops"})],
)
def test_dependency_direction(package: str, forbidden: set[str]) -> None:
    for path in (ROOT / package).rglob("*.py"):
        bad = _imports(path) & forbidden
        assert not bad, f"{path.relative_to(ROOT)} imports {bad}"


def test_no_source_file_outside_benchmarks_is_over_400_lines() -> None:
    too_long = {str(p.relative_to(ROOT)): n for folder in ("morpheus_core", "ops", "assets_store", "orchestration",
                                                           "tests")
                for p in (ROOT / folder).rglob("*.py") if (n := len(p.read_text().splitlines())) > 400}
    assert not too_long, f"split these by what they hold: {too_long}"


def test_the_engine_and_the_stages_never_import_the_command_line_or_the_reports() -> None:
    for package in ("ops/engine", "ops/stages", "ops/config", "ops/intake"):
        for path in (ROOT / package).rglob("*.py"):
            modules = {node.module for node in ast.walk(ast.parse(path.read_text()))
                       if isinstance(node, ast.ImportFrom) and node.module}
            bad = {m for m in modules if m == "ops.cli" or m.startswith("ops.reporting")}
            assert not bad, f"{path.relative_to(ROOT)} imports {bad}"
