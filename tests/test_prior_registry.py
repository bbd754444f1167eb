"""Model registry and offline loading: present/missing folders, typed errors, no network."""

from __future__ import annotations

import os
import shutil
import socket
from pathlib import Path

import pytest
import torch

from morpheus_core.priors.image2d import Image2DPrior, Image2DSettings
from morpheus_core.priors.registry import MODEL_SPECS, ModelMissingError, ModelRegistry
from morpheus_core.priors.zero123 import CameraProjection, Zero123Prior
from tests.helpers import RES_2D, photo


def test_every_model_folder_written_by_save_pretrained_is_present(registry: ModelRegistry) -> None:
    statuses = registry.statuses()
    assert [s.spec.name for s in statuses] == [s.name for s in MODEL_SPECS]
    assert all(s.present for s in statuses), [(s.spec.name, s.missing) for s in statuses]
    assert registry.prior_ready("3d") and registry.prior_ready("2d")


def test_registry_root_and_folder_overrides(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MORPHEUS_MODELS", str(tmp_path / "env"))
    assert ModelRegistry().resolved_root() == (tmp_path / "env", "$MORPHEUS_MODELS")
    reg = ModelRegistry(root=tmp_path, folders={"zero123": Path("/abs/z123")})
    assert reg.resolved_root() == (tmp_path, "config")
    assert reg.folder("zero123") == Path("/abs/z123") and reg.folder("sd15") == tmp_path / "stable-diffusion-v1-5"
    with pytest.raises(KeyError, match="zero12"):
        ModelRegistry(folders={"zero12": Path("x")})


def test_priors_load_offline_with_the_network_blocked(registry: ModelRegistry, monkeypatch) -> None:
    def refuse(*args, **kwargs):
        raise AssertionError("a prior tried to open a network connection")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    assert os.environ.get("HF_HUB_OFFLINE") == "1"
    z = Zero123Prior.from_registry(registry)
    p = Image2DPrior.from_registry(registry, settings=Image2DSettings(resolution=RES_2D))
    z.set_reference("o", photo(0))
    p.set_reference("o", photo(0))
    assert z.object_ids == ("o",) and p.object_ids == ("o",)


@pytest.mark.parametrize(
    "model,victim",
    [("zero123", "unet/diffusion_pytorch_model.safetensors"),
     ("zero123", "cc_projection/config.json"),
     ("zero123", "feature_extractor/preprocessor_config.json"),
     ("sd15", "text_encoder/model.safetensors"),
     ("controlnet_canny", "config.json"),
     ("ip_adapter", "models/ip-adapter_sd15.safetensors")],
)
def test_a_missing_file_raises_the_typed_error_naming_it(models_root: Path, tmp_path: Path, model: str,
                                                         victim: str) -> None:
    shutil.copytree(models_root, tmp_path, dirs_exist_ok=True)
    reg = ModelRegistry(root=tmp_path)
    (reg.folder(model) / victim).unlink()
    load = Zero123Prior.from_registry if model == "zero123" else Image2DPrior.from_registry
    with pytest.raises(ModelMissingError) as exc:
        load(reg)
    err = exc.value
    assert err.folder == reg.folder(model) and any(victim in m for m in err.missing)
    assert victim in str(err) and str(reg.folder(model)) in str(err) and "To provide it" in str(err)
    assert isinstance(err, FileNotFoundError)


def test_both_camera_projection_layouts_load_the_same_weights(models_root: Path) -> None:
    a = CameraProjection.from_folder(models_root / "zero123-xl")  # cc_projection, projection.*
    b = CameraProjection.from_folder(models_root / "zero123-alt")  # clip_camera_projection, proj.*
    assert a.linear.in_features == a.linear.out_features + 4
    assert torch.equal(a.linear.weight, b.linear.weight) and torch.equal(a.linear.bias, b.linear.bias)


def test_a_projection_with_wrong_keys_is_rejected(models_root: Path, tmp_path: Path) -> None:
    from safetensors.torch import save_file

    folder = tmp_path / "cc_projection"
    folder.mkdir()
    (folder / "config.json").write_text("{}")
    save_file({"linear.weight": torch.zeros(8, 12)}, str(folder / "diffusion_pytorch_model.safetensors"))
    with pytest.raises(KeyError, match=r"projection\.weight"):
        CameraProjection.from_folder(tmp_path)
