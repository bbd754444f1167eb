"""rembg path: a tiny U²-Net-shaped ONNX model under a temporary $U2NET_HOME, and no network ever."""

from __future__ import annotations

import socket
import sys
import types
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper
from PIL import Image

from morpheus_core.segmentation.mask_ops import iou
from ops.intake.prepare import prepare_reference
from ops.intake.rembg_local import INPUT_SIZE, U2NetSession
from ops.intake.segment import SegmentConfig, Segmenter
from tests.photo_factory import PhotoSpec, product_photo


def build_u2net_like(path: Path, weight: float = -4.0, bias: float = -2.0) -> Path:
    """1×3×320×320 input ``input.1`` → seven 1×1×320×320 sigmoid maps, like u2net.onnx's d0..d6.

    The map is sigmoid(weight·Σ channels + bias) of the ImageNet-normalised input: with a
    negative weight it marks dark pixels, i.e. a dark product on a white backdrop.
    """
    shape = [1, 3, INPUT_SIZE, INPUT_SIZE]
    out_shape = [1, 1, INPUT_SIZE, INPUT_SIZE]
    w = helper.make_tensor("w", TensorProto.FLOAT, [1, 3, 1, 1], [weight] * 3)
    b = helper.make_tensor("b", TensorProto.FLOAT, [1], [bias])
    nodes = [helper.make_node("Conv", ["input.1", "w", "b"], ["logits"]),
             helper.make_node("Sigmoid", ["logits"], ["d0"])]
    nodes += [helper.make_node("Identity", ["d0"], [f"d{i}"]) for i in range(1, 7)]
    graph = helper.make_graph(
        nodes, "tiny_u2net", [helper.make_tensor_value_info("input.1", TensorProto.FLOAT, shape)],
        [helper.make_tensor_value_info(f"d{i}", TensorProto.FLOAT, out_shape) for i in range(7)], [w, b],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    path.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(model, path)
    return path


@pytest.fixture
def no_network(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Every way out to the network raises (and is recorded); importing pooch fails too."""
    attempts: list[str] = []

    def refuse(*args, **kwargs):
        attempts.append(repr(args[:2]))
        raise OSError("network access attempted during segmentation")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket.socket, "connect_ex", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)
    monkeypatch.setattr(socket, "getaddrinfo", refuse)
    monkeypatch.setitem(sys.modules, "pooch", None)  # rembg's downloader: any import now raises
    return attempts


def _dark_product(tmp_path: Path, seed: int) -> tuple[Path, np.ndarray]:
    rgb, truth = product_photo(PhotoSpec("cylinder", "white", "flat", seed, size=256))
    rgb = (rgb * 0.35).astype(np.uint8)  # dark product…
    rgb[~truth] = 240  # …on a plain white backdrop, so the tiny model's "darkness" is a real mask
    path = tmp_path / f"dark_{seed}.png"
    Image.fromarray(rgb).save(path)
    return path, truth


def test_rembg_model_from_u2net_home_is_used_and_recorded(tmp_path, monkeypatch, no_network) -> None:
    home = tmp_path / "u2net_home"
    model = build_u2net_like(home / "u2net.onnx")
    monkeypatch.setenv("U2NET_HOME", str(home))
    created = []
    original_init = U2NetSession.__init__

    def counting_init(self, *args, **kwargs):
        created.append(args[0])
        original_init(self, *args, **kwargs)

    monkeypatch.setattr(U2NetSession, "__init__", counting_init)
    segmenter = Segmenter()
    for seed in (21, 22):
        photo, truth = _dark_product(tmp_path, seed)
        info = prepare_reference(photo, tmp_path / f"ref_{seed}", segmenter=segmenter)
        assert info.method == "rembg" and info.model_path == str(model)
        assert [(c.step, c.outcome) for c in info.chain] == [("alpha", "skipped"), ("rembg", "used")]
        mask = np.asarray(Image.open(tmp_path / f"ref_{seed}" / "mask_512.png")) >= 128
        assert mask.mean() > 0.1  # the model's (dark-pixel) mask made it to the outputs
        x0, y0, x1, y1 = info.bbox
        tx, ty = np.nonzero(truth.any(axis=0))[0], np.nonzero(truth.any(axis=1))[0]
        assert abs(x0 - tx[0]) <= 3 and abs(x1 - tx[-1] - 1) <= 3 and abs(y0 - ty[0]) <= 3 and abs(y1 - ty[-1] - 1) <= 3
    assert created == [model]  # one session for both photos
    assert no_network == []


def test_no_model_falls_back_to_classical_without_network(tmp_path, monkeypatch, no_network) -> None:
    monkeypatch.setenv("U2NET_HOME", str(tmp_path / "empty_home"))
    photo, _truth = _dark_product(tmp_path, 23)
    info = prepare_reference(photo, tmp_path / "ref")
    assert info.method == "classical" and info.model_path is None
    rembg_step = next(c for c in info.chain if c.step == "rembg")
    assert rembg_step.outcome == "skipped" and "no u2net model at" in rembg_step.detail
    assert str(tmp_path / "empty_home" / "u2net.onnx") in rembg_step.detail
    assert no_network == []


def test_configured_model_folder_and_disabled_rembg(tmp_path, monkeypatch, no_network) -> None:
    monkeypatch.setenv("U2NET_HOME", str(tmp_path / "nothing_here"))
    model = build_u2net_like(tmp_path / "models" / "u2net.onnx")
    photo, _ = _dark_product(tmp_path, 24)
    seg = Segmenter(SegmentConfig(rembg_model=model.parent))
    assert prepare_reference(photo, tmp_path / "a", segmenter=seg).model_path == str(model)
    off = Segmenter(SegmentConfig(use_rembg=False, rembg_model=model.parent))
    info = prepare_reference(photo, tmp_path / "b", segmenter=off)
    assert info.method == "classical" and "disabled" in info.chain[1].detail


def test_useless_model_output_is_rejected_then_classical(tmp_path, no_network) -> None:
    model = build_u2net_like(tmp_path / "flat" / "u2net.onnx", weight=0.0, bias=0.0)  # constant map
    photo, _truth = _dark_product(tmp_path, 25)
    info = prepare_reference(photo, tmp_path / "ref", segmenter=Segmenter(SegmentConfig(rembg_model=model)))
    assert [(c.step, c.outcome) for c in info.chain] == [("alpha", "skipped"), ("rembg", "rejected"),
                                                         ("classical", "used")]
    assert "mask is empty" in info.chain[1].detail


def _no_matting(*args: object, **kwargs: object) -> None:
    raise AssertionError("alpha matting is not part of the session under test")


def test_matches_rembg_own_custom_session(tmp_path, monkeypatch) -> None:
    """Same pre/post-processing as rembg's U2netCustomSession on the same model and image."""
    # Importing the rembg package JIT-compiles pymatting's alpha-matting kernels with numba (about 60 s
    # on 2 cores in every fresh venv); the session compared here never mattes, so pymatting is stubbed.
    for name in ("pymatting", "pymatting.alpha", "pymatting.alpha.estimate_alpha_cf", "pymatting.foreground",
                 "pymatting.foreground.estimate_foreground_ml", "pymatting.util", "pymatting.util.util"):
        stub = types.ModuleType(name)
        stub.estimate_alpha_cf = stub.estimate_foreground_ml = stub.stack_images = _no_matting  # type: ignore[attr-defined]
        monkeypatch.setitem(sys.modules, name, stub)
    for name in [m for m in sys.modules if m == "rembg" or m.startswith("rembg.")]:
        monkeypatch.delitem(sys.modules, name)  # imported afresh on the stubs, and dropped after the test
    rembg_sessions = pytest.importorskip("rembg.sessions.u2net_custom")
    import onnxruntime as ort

    monkeypatch.setenv("U2NET_HOME", str(tmp_path))
    model = build_u2net_like(tmp_path / "u2net.onnx", weight=-2.0, bias=1.0)
    rgb, _ = product_photo(PhotoSpec("blob", "grey", "print", 26, size=200))
    theirs = rembg_sessions.U2netCustomSession("u2net_custom", ort.SessionOptions(), model_path=str(model),
                                               providers=["CPUExecutionProvider"])
    expected = np.asarray(theirs.predict(Image.fromarray(rgb))[0], dtype=np.float32) / 255.0
    ours = U2NetSession(model).predict(rgb.astype(np.float32) / 255.0)
    assert ours.shape == expected.shape and np.abs(ours - expected).max() <= 1.0 / 255.0 + 1e-6
    assert iou(ours > 0.5, expected > 0.5) > 0.999
