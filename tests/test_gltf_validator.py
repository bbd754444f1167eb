"""The Khronos glTF-Validator wrapper (``morpheus_core.export.gltf_validator``): both GLB exports pass it
with 0 errors, and it does fail broken files (so a green check means something).

Tests that run the validator skip, saying what to install, where Node.js or tools/web is missing.
"""

from __future__ import annotations

import json
import os
import struct
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from morpheus_core.export.glb_geometry import meshopt_available
from morpheus_core.export.gltf import encode_glb
from morpheus_core.export.gltf_validator import (
    TOOLS_ENV,
    GltfValidation,
    ValidatorUnavailable,
    parse_report,
    validate_gltf,
    validator_available,
)
from morpheus_core.export.web_glb import encode_web_glb
from tests.test_web_glb import random_baked


@pytest.fixture
def rng() -> np.random.Generator:
    seed = int(os.environ.get("WEB_GLB_SEED", np.random.SeedSequence().entropy % 2**63))
    print(f"WEB_GLB_SEED={seed}")
    return np.random.default_rng(seed)


@pytest.fixture
def validator() -> None:
    missing = validator_available()
    if missing is not None:
        pytest.skip(missing)


def _validate(data: bytes, path: Path) -> GltfValidation:
    path.write_bytes(data)
    return validate_gltf(path)


def _split_glb(data: bytes) -> tuple[dict[str, Any], bytearray]:
    json_len = struct.unpack_from("<I", data, 12)[0]
    return json.loads(data[20:20 + json_len]), bytearray(data[28 + json_len:])


def _join_glb(doc: dict[str, Any], bin_chunk: bytes) -> bytes:
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    total = 28 + len(text) + len(bin_chunk)
    return (struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<II", len(text), 0x4E4F534A) + text
            + struct.pack("<II", len(bin_chunk), 0x004E4942) + bytes(bin_chunk))


# ------------------------------------------------------------------------------- valid exports


@pytest.mark.parametrize("compression", ["auto", "none"])
def test_web_glb_has_no_errors(validator: None, rng: np.random.Generator, tmp_path: Path, compression: str) -> None:
    data, report = encode_web_glb(random_baked(rng), 50_000_000, compression=compression)
    result = _validate(data, tmp_path / "web.glb")
    assert result.errors == 0 and result.warnings == 0, result.messages
    assert result.validator_version.startswith("2.")
    expected_infos = set()
    if "EXT_meshopt_compression" in report.extensions:
        # The validator does not know meshopt: it says so, once, and cannot check the compressed views.
        expected_infos.add("UNSUPPORTED_EXTENSION")
    else:
        # Quantized views are fully checked (min/max, index ranges, unit normals).
        assert compression == "none" or meshopt_available() is not None
    size = report.texture_size
    if size & (size - 1):
        expected_infos.add("IMAGE_NPOT_DIMENSIONS")  # WebGL 2 (model-viewer, three.js) mipmaps these fine
    assert set(result.info_codes) == expected_infos and result.infos == len(expected_infos)


def test_editing_glb_has_no_errors(validator: None, rng: np.random.Generator, tmp_path: Path) -> None:
    result = _validate(encode_glb(random_baked(rng)), tmp_path / "edit.glb")
    assert result.ok and result.errors == 0 and result.warnings == 0, result.messages


# ------------------------------------------------------------------------------ broken exports


def test_truncated_glb_has_errors(validator: None, rng: np.random.Generator, tmp_path: Path) -> None:
    data, _ = encode_web_glb(random_baked(rng), 50_000_000, compression="none")
    result = _validate(data[: len(data) * 2 // 3], tmp_path / "cut.glb")
    assert not result.ok and result.errors > 0
    assert result.error_messages and all(m.code for m in result.error_messages)


def test_index_out_of_range_has_errors(validator: None, rng: np.random.Generator, tmp_path: Path) -> None:
    baked = random_baked(rng)
    doc, bin_chunk = _split_glb(encode_web_glb(baked, 50_000_000, compression="none")[0])
    indices = doc["accessors"][doc["meshes"][0]["primitives"][0]["indices"]]
    view = doc["bufferViews"][indices["bufferView"]]
    assert indices["componentType"] == 5123
    struct.pack_into("<H", bin_chunk, view["byteOffset"] + 2 * 7, len(baked.vertices) + 5)
    result = _validate(_join_glb(doc, bin_chunk), tmp_path / "oob.glb")
    assert result.errors > 0
    assert "ACCESSOR_INDEX_OOB" in {m.code for m in result.error_messages}


def test_accessor_past_its_buffer_view_has_errors(validator: None, rng: np.random.Generator,
                                                  tmp_path: Path) -> None:
    doc, bin_chunk = _split_glb(encode_web_glb(random_baked(rng), 50_000_000, compression="none")[0])
    doc["accessors"][0]["count"] += 1000
    result = _validate(_join_glb(doc, bin_chunk), tmp_path / "long.glb")
    assert result.errors > 0
    assert any(m.pointer and m.pointer.startswith("/accessors/0") for m in result.error_messages)


# ------------------------------------------------------------------------------ without the tool


def test_missing_tools_dir_says_the_fix(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # Any executable passes the node lookup, so this runs without Node.js.
    message = validator_available(tools_dir=tmp_path, node=sys.executable)
    assert message is not None and "make web-tools" in message and "npm ci --prefix tools/web" in message
    assert str(tmp_path) in message
    monkeypatch.setenv(TOOLS_ENV, str(tmp_path))
    assert validator_available(node=sys.executable) == message
    (tmp_path / "x.glb").write_bytes(b"glTF")
    with pytest.raises(ValidatorUnavailable, match="make web-tools"):
        validate_gltf(tmp_path / "x.glb", node=sys.executable)


def test_missing_node_says_the_fix(tmp_path: Path) -> None:
    message = validator_available(node=str(tmp_path / "no-such-node"))
    assert message is not None and "Node.js" in message
    with pytest.raises(ValidatorUnavailable, match=r"Node\.js"):
        validate_gltf(tmp_path / "x.glb", node=str(tmp_path / "no-such-node"))


def test_missing_file(validator: None, tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        validate_gltf(tmp_path / "absent.glb")


def test_parse_report_counts_and_keeps_errors_and_warnings() -> None:
    report = {
        "validatorVersion": "2.0.0-dev.3.10",
        "issues": {
            "numErrors": 1, "numWarnings": 1, "numInfos": 2, "numHints": 1,
            "messages": [
                {"code": "GLB_UNEXPECTED_END_OF_CHUNK_DATA", "message": "cut", "severity": 0, "offset": 120},
                {"code": "MESH_PRIMITIVE_GENERATED_TANGENT_SPACE", "message": "w", "severity": 1,
                 "pointer": "/meshes/0"},
                {"code": "UNSUPPORTED_EXTENSION", "message": "i", "severity": 2, "pointer": "/extensionsUsed/1"},
                {"code": "UNUSED_OBJECT", "message": "i2", "severity": 2, "pointer": "/accessors/3"},
                {"code": "BUFFER_VIEW_TARGET_MISSING", "message": "h", "severity": 3, "pointer": "/bufferViews/0"},
            ],
        },
    }
    result = parse_report(report)
    assert (result.errors, result.warnings, result.infos, result.hints) == (1, 1, 2, 1)
    assert [m.severity for m in result.messages] == ["error", "warning"]
    assert result.error_messages[0].pointer == "@120"
    assert result.warning_messages[0].pointer == "/meshes/0"
    assert result.info_codes == ("UNSUPPORTED_EXTENSION", "UNUSED_OBJECT")
    assert not result.ok and result.validator_version == "2.0.0-dev.3.10"
