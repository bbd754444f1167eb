"""Weighted QA metrics: skip records without weights, tiny random stand-ins through the real
loading and scoring code, LPIPS/CLIP properties, corrupt files, the LPIPS converter."""

from __future__ import annotations

import math
import re
import shutil
import socket
from pathlib import Path

import pytest
import torch

from morpheus_core.metrics.lpips import LPIPS, LPIPS_FILE, LPIPSWeightsError, convert_lpips_checkpoint, main
from morpheus_core.metrics.weighted import (
    METRIC_NAMES,
    SKIP_MISSING,
    WeightedMetrics,
    WeightedMetricsConfig,
    compute_weighted_metrics,
    weighted_metric_status,
)
from morpheus_core.metrics.weighted_models import MANIQA_FILE
from tests.helpers import photo
from tests.tiny_models import tiny_lpips, write_tiny_maniqa, write_weighted_metric_models

EXPECTED = {
    "lpips": ("lpips", [LPIPS_FILE]),
    "clip_similarity": ("clip", ["config.json", "model.safetensors or pytorch_model.bin", "preprocessor_config.json"]),
    "clipiqa": ("clip", ["config.json", "model.safetensors or pytorch_model.bin", "preprocessor_config.json",
                         "tokenizer.json or vocab.json"]),
    "maniqa": ("maniqa", [MANIQA_FILE]),
}


@pytest.fixture(scope="module")
def metric_models(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_weighted_metric_models(tmp_path_factory.mktemp("metric_models"))


@pytest.fixture(scope="module")
def scorer(metric_models: Path) -> WeightedMetrics:
    """Shared: loads each tiny model once for the whole file, as a catalog run would."""
    return WeightedMetrics(WeightedMetricsConfig(models_root=metric_models, batch_size=2))


def _photo() -> tuple[torch.Tensor, torch.Tensor]:
    rgba = photo(0)
    return rgba[:3], rgba[3]


def _views(n: int = 3, size: int = 48) -> torch.Tensor:
    return torch.stack([photo(10 + i, size=size, rgba=False) for i in range(n)])


def test_missing_weights_skip_every_metric_listing_the_expected_files(tmp_path: Path, monkeypatch) -> None:
    def refuse(*args, **kwargs):
        raise AssertionError("a metric tried to open a network connection")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    cfg = WeightedMetricsConfig(models_root=tmp_path / "empty")
    ref, mask = _photo()
    results = compute_weighted_metrics(ref, mask, _views(), cfg)
    assert list(results) == list(METRIC_NAMES)
    for name, (sub, files) in EXPECTED.items():
        r = results[name]
        assert (r.name, r.status, r.value, r.per_view) == (name, "skipped", None, ())
        assert r.detail.startswith(SKIP_MISSING) and SKIP_MISSING == "skipped: weights missing (expected files "
        assert str(tmp_path / "empty" / sub) in r.detail
        for f in files:
            assert f in r.detail, (name, f, r.detail)
        assert "never downloaded" in r.detail
    statuses = weighted_metric_status(cfg)
    assert [s.spec.name for s in statuses] == list(METRIC_NAMES)
    assert all(not s.present and s.enabled for s in statuses)
    assert {s.spec.name: list(s.missing) for s in statuses} == {n: f for n, (_, f) in EXPECTED.items()}


def test_a_partial_folder_names_only_the_absent_file(metric_models: Path, tmp_path: Path) -> None:
    shutil.copytree(metric_models, tmp_path, dirs_exist_ok=True)
    (tmp_path / "clip" / "preprocessor_config.json").unlink()
    (tmp_path / "clip" / "tokenizer.json").unlink()  # vocab.json is the alternative: the tokenizer stays present
    results = compute_weighted_metrics(*_photo(), _views(), WeightedMetricsConfig(models_root=tmp_path))
    for name in ("clip_similarity", "clipiqa"):
        assert results[name].status == "skipped"
        assert results[name].detail.split("missing: ")[1].startswith("preprocessor_config.json)")
    assert results["lpips"].status == results["maniqa"].status == "ok"


def test_every_metric_gives_a_finite_number_through_the_real_code_path(scorer: WeightedMetrics) -> None:
    assert all(s.present for s in scorer.status())
    ref, mask = _photo()
    views = _views(3)
    results = scorer.compute(ref, mask, views)
    for name, r in results.items():
        assert r.status == "ok", r.detail
        assert r.value is not None and math.isfinite(r.value), name
    for name in ("clip_similarity", "clipiqa", "maniqa"):
        assert len(results[name].per_view) == 3
        assert results[name].value == pytest.approx(sum(results[name].per_view) / 3, rel=1e-6)
    assert 0.0 <= results["clipiqa"].value <= 1.0
    assert -1.0 <= results["clip_similarity"].value <= 1.0
    assert 0.0 < results["maniqa"].value < 1.0  # the stand-in ends in a sigmoid
    # CLIP similarity and CLIP-IQA share the clip/ folder: one CLIPModel is loaded for both.
    assert len(scorer._clip) == 1


def test_lpips_is_zero_for_identical_images_symmetric_and_grows_with_noise(metric_models: Path) -> None:
    net = LPIPS.from_file(metric_models / "lpips" / LPIPS_FILE)
    x = photo(3, size=64, rgba=False)[None]
    g = torch.Generator().manual_seed(0)
    noise = torch.randn(x.shape, generator=g)
    with torch.no_grad():
        assert float(net(x, x)[0]) < 1e-6
        d = [float(net(x, (x + s * noise).clamp(0, 1))[0]) for s in (0.02, 0.1, 0.4)]
        y = (x + 0.1 * noise).clamp(0, 1)
        assert float(net(x, y)[0]) == pytest.approx(float(net(y, x)[0]), abs=1e-6)
    assert 0.0 < d[0] < d[1] < d[2], d


def test_lpips_through_compute_is_zero_for_the_photo_itself(scorer: WeightedMetrics) -> None:
    ref, mask = _photo()
    on_white = ref * mask + (1 - mask)
    same = scorer.compute(ref, mask, _views(), reference_render=on_white)["lpips"]
    assert same.status == "ok" and same.value < 1e-6
    other = scorer.compute(ref, mask, _views(), reference_render=photo(7, rgba=False))["lpips"]
    assert other.value > 1e-3
    # A render at another size is resized to the photo's; views[0] is the default reference render.
    big = torch.nn.functional.interpolate(on_white[None], size=(96, 96), mode="bilinear")[0]
    resized = scorer.compute(ref, mask, torch.stack([big, big]))["lpips"]
    assert resized.status == "ok" and resized.value < other.value


def test_clip_similarity_of_identical_images_is_one_and_clipiqa_is_a_probability(scorer: WeightedMetrics) -> None:
    ref = photo(4, size=40, rgba=False)
    results = scorer.compute(ref, None, torch.stack([ref, ref, ref]))
    sim = results["clip_similarity"]
    assert sim.value == pytest.approx(1.0, abs=1e-5)
    assert all(v == pytest.approx(1.0, abs=1e-5) for v in sim.per_view)
    iqa = results["clipiqa"]
    assert 0.0 <= iqa.value <= 1.0
    # The tiny vocabulary spells both prompts, so they embed differently and the pair is not a tie.
    assert abs(iqa.value - 0.5) > 1e-4
    noisy = (ref + 0.5 * torch.randn(ref.shape, generator=torch.Generator().manual_seed(1))).clamp(0, 1)
    assert scorer.compute(ref, None, noisy[None])["clip_similarity"].value < 1.0 - 1e-4


def test_maniqa_with_a_fixed_batch_is_fed_in_chunks(metric_models: Path, tmp_path: Path,
                                                    scorer: WeightedMetrics) -> None:
    write_tiny_maniqa(tmp_path / "fixed" / MANIQA_FILE, fixed_batch=1)  # same seed: same weights
    fixed = WeightedMetrics(WeightedMetricsConfig(models_root=metric_models, folders={"maniqa": tmp_path / "fixed"},
                                                  enabled=frozenset({"maniqa"}), batch_size=4))
    views = _views(3)
    a = fixed.compute(*_photo(), views)["maniqa"]
    b = scorer.compute(*_photo(), views)["maniqa"]
    assert a.status == b.status == "ok"
    assert a.per_view == pytest.approx(b.per_view, abs=1e-6)


def test_broken_files_give_error_records_naming_the_file(metric_models: Path, tmp_path: Path) -> None:
    shutil.copytree(metric_models, tmp_path, dirs_exist_ok=True)
    lpips_file = tmp_path / "lpips" / LPIPS_FILE
    lpips_file.write_bytes(lpips_file.read_bytes()[:100])  # truncated
    write_tiny_maniqa(tmp_path / "maniqa" / MANIQA_FILE, channels=1)  # breaks the N×3×224×224 contract
    with pytest.raises(LPIPSWeightsError, match=re.escape(LPIPS_FILE)):
        LPIPS.from_file(lpips_file)
    scorer = WeightedMetrics(WeightedMetricsConfig(models_root=tmp_path))
    for _ in range(2):  # the second call reports the remembered load error
        results = scorer.compute(*_photo(), _views())
        assert results["lpips"].status == "error" and results["lpips"].value is None
        assert str(lpips_file) in results["lpips"].detail
        assert results["maniqa"].status == "error" and MANIQA_FILE in results["maniqa"].detail
        assert results["clip_similarity"].status == results["clipiqa"].status == "ok"  # the rest still ran


def test_lpips_with_another_key_layout_is_a_typed_error(tmp_path: Path) -> None:
    from safetensors.torch import save_file

    state = {k: v.contiguous() for k, v in tiny_lpips().state_dict().items() if k != "lin.4.weight"}
    save_file(state, str(tmp_path / LPIPS_FILE))
    with pytest.raises(LPIPSWeightsError, match=re.escape("lin.4.weight")):
        LPIPS.from_file(tmp_path / LPIPS_FILE)


def test_default_lpips_networks_have_the_original_sizes() -> None:
    alex = {k: tuple(v.shape) for k, v in LPIPS("alex").state_dict().items()}
    assert alex == {
        "features.0.weight": (64, 3, 11, 11), "features.0.bias": (64,),
        "features.3.weight": (192, 64, 5, 5), "features.3.bias": (192,),
        "features.6.weight": (384, 192, 3, 3), "features.6.bias": (384,),
        "features.8.weight": (256, 384, 3, 3), "features.8.bias": (256,),
        "features.10.weight": (256, 256, 3, 3), "features.10.bias": (256,),
        "lin.0.weight": (1, 64, 1, 1), "lin.1.weight": (1, 192, 1, 1), "lin.2.weight": (1, 384, 1, 1),
        "lin.3.weight": (1, 256, 1, 1), "lin.4.weight": (1, 256, 1, 1),
    }
    vgg = {k: tuple(v.shape) for k, v in LPIPS("vgg16").state_dict().items()}
    convs = [0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28]  # torchvision vgg16.features indices
    assert sorted(int(k.split(".")[1]) for k in vgg if k.startswith("features") and k.endswith("weight")) == convs
    assert vgg["features.28.weight"] == (512, 512, 3, 3)
    assert [vgg[f"lin.{k}.weight"][1] for k in range(5)] == [64, 128, 256, 512, 512]


@pytest.mark.parametrize("net", ["alex", "vgg16"])
def test_converter_maps_the_official_checkpoint_layout(tmp_path: Path, net: str) -> None:
    """torchvision trunk (features.* + classifier.*) and LPIPS heads (lin<k>.model.1.weight) as .pth
    files → lpips.safetensors, which scores exactly like the network they came from."""
    src = tiny_lpips(seed=5, net=net)
    trunk = {k: v for k, v in src.state_dict().items() if k.startswith("features.")}
    trunk["classifier.1.weight"] = torch.zeros(4, 4)  # dropped by the converter
    lin = {f"lin{k}.model.1.weight": src.lin[k].weight.detach().clone() for k in range(5)}
    torch.save(trunk, tmp_path / "trunk.pth")
    torch.save(lin, tmp_path / "lin.pth")
    out = tmp_path / "lpips" / LPIPS_FILE
    if net == "alex":
        args = ["--trunk", str(tmp_path / "trunk.pth"), "--lin", str(tmp_path / "lin.pth"), "--out", str(out)]
        assert main(args) == 0
    else:
        convert_lpips_checkpoint(tmp_path / "trunk.pth", tmp_path / "lin.pth", out)
    loaded = LPIPS.from_file(out)
    assert loaded.trunk.name == net
    x, y = photo(1, size=40, rgba=False)[None], photo(2, size=40, rgba=False)[None]
    with torch.no_grad():
        assert torch.equal(loaded(x, y), src(x, y))
    with pytest.raises(LPIPSWeightsError, match="lin0"):
        convert_lpips_checkpoint(tmp_path / "trunk.pth", tmp_path / "trunk.pth", tmp_path / "bad.safetensors")


def test_config_validation_overrides_and_disabled_metrics(tmp_path: Path, monkeypatch, metric_models: Path) -> None:
    monkeypatch.setenv("MORPHEUS_MODELS", str(tmp_path / "env"))
    assert WeightedMetricsConfig().folder("lpips") == tmp_path / "env" / "lpips"
    cfg = WeightedMetricsConfig(models_root=tmp_path, folders={"clipiqa": Path("other-clip"), "maniqa": Path("/abs/m")})
    assert cfg.folder("clipiqa") == tmp_path / "other-clip" and cfg.folder("clip_similarity") == tmp_path / "clip"
    assert cfg.folder("maniqa") == Path("/abs/m")
    with pytest.raises(KeyError, match="lpip"):
        WeightedMetricsConfig(folders={"lpip": Path("x")})
    with pytest.raises(KeyError, match="clip_iqa"):
        WeightedMetricsConfig(enabled=frozenset({"clip_iqa"}))
    with pytest.raises(ValueError, match="batch_size"):
        WeightedMetricsConfig(batch_size=0)
    only = WeightedMetricsConfig(models_root=metric_models, enabled=frozenset({"lpips"}))
    results = compute_weighted_metrics(*_photo(), _views(), only)
    assert results["lpips"].status == "ok"
    assert all(results[n].status == "skipped" and "disabled" in results[n].detail for n in METRIC_NAMES[1:])
    assert [s.enabled for s in weighted_metric_status(only)] == [True, False, False, False]


def test_invalid_inputs_raise(scorer: WeightedMetrics) -> None:
    ref, mask = _photo()
    with pytest.raises(ValueError, match="reference"):
        scorer.compute(ref[None], mask, _views())
    with pytest.raises(ValueError, match="views"):
        scorer.compute(ref, mask, _views()[:, :2])
    with pytest.raises(ValueError, match="reference_mask"):
        scorer.compute(ref, mask[:10], _views())
    bad = _views()
    bad[0, 0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        scorer.compute(ref, mask, bad)


def _upstream_lpips_alex(state: dict[str, torch.Tensor], in0: torch.Tensor, in1: torch.Tensor) -> torch.Tensor:
    """LPIPS v0.1 (alex) transcribed step by step from richzhang/PerceptualSimilarity with plain
    functional ops, independent of ``morpheus_core.metrics.lpips``'s module structure: inputs in [-1, 1],
    ScalingLayer, slices features[0:2], [2:5], [5:8], [8:10], [10:12], normalize_tensor, heads."""
    F = torch.nn.functional
    shift = torch.tensor([-.030, -.088, -.188])[None, :, None, None]
    scale = torch.tensor([.458, .448, .450])[None, :, None, None]

    def trunk(x: torch.Tensor) -> list[torch.Tensor]:
        h1 = F.relu(F.conv2d(x, state["features.0.weight"], state["features.0.bias"], stride=4, padding=2))
        h2 = F.relu(F.conv2d(F.max_pool2d(h1, 3, 2), state["features.3.weight"], state["features.3.bias"], padding=2))
        h3 = F.relu(F.conv2d(F.max_pool2d(h2, 3, 2), state["features.6.weight"], state["features.6.bias"], padding=1))
        h4 = F.relu(F.conv2d(h3, state["features.8.weight"], state["features.8.bias"], padding=1))
        h5 = F.relu(F.conv2d(h4, state["features.10.weight"], state["features.10.bias"], padding=1))
        return [h1, h2, h3, h4, h5]

    def normalize_tensor(f: torch.Tensor, eps: float = 1e-10) -> torch.Tensor:
        return f / (torch.sqrt(torch.sum(f**2, dim=1, keepdim=True)) + eps)

    outs0, outs1 = trunk((in0 - shift) / scale), trunk((in1 - shift) / scale)
    val = 0
    for k in range(5):
        diff = (normalize_tensor(outs0[k]) - normalize_tensor(outs1[k])) ** 2
        val = val + F.conv2d(diff, state[f"lin.{k}.weight"]).mean([2, 3], keepdim=True)
    return val.reshape(-1)


def test_lpips_matches_a_transcription_of_the_reference_formula(metric_models: Path) -> None:
    """Same weights, two implementations: catches a wrong tap, constant or head mapping. (Parity
    with the published LPIPS numbers needs the real weights, which are not available offline.)"""
    from safetensors.torch import load_file

    state = load_file(str(metric_models / "lpips" / LPIPS_FILE))
    net = LPIPS.from_file(metric_models / "lpips" / LPIPS_FILE)
    x = torch.stack([photo(i, size=64, rgba=False) for i in range(3)])
    y = torch.stack([photo(i + 20, size=64, rgba=False) for i in range(3)])
    with torch.no_grad():
        ours = net(x, y)
        ref = _upstream_lpips_alex(state, 2 * x - 1, 2 * y - 1)  # upstream's normalize=True for [0, 1] input
    torch.testing.assert_close(ours, ref, rtol=1e-5, atol=1e-7)
    assert bool((ours > 0).all())
