"""The manifest of one finished stage output: what went in, what came out, and how it ran.

``manifest.json`` is written last into a stage folder and is its completion marker: a folder
without a valid manifest is not a finished output. The file is strict JSON (no NaN/Infinity
literals) so any JSON reader can load it; non-finite floats are spelled "inf", "-inf", "nan".
"""

from __future__ import annotations

import json
import math
import numbers
import re
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields
from datetime import datetime, timezone
from pathlib import PurePosixPath
from typing import Any

MANIFEST_FILE = "manifest.json"
SCHEMA = 1

_SHA256 = re.compile(r"[0-9a-f]{64}")
_NON_FINITE = {"inf": math.inf, "-inf": -math.inf, "nan": math.nan}


def utc_now() -> str:
    """The current time as ISO-8601 UTC, e.g. ``2025-01-31T12:00:00.123456+00:00``."""
    return datetime.now(timezone.utc).isoformat()


@dataclass(frozen=True)
class FileRecord:
    """One output file: its content hash and size in bytes."""

    sha256: str
    size: int


@dataclass(frozen=True)
class Fingerprint:
    """Everything that decides a stage's output: a stage is reused only on an equal fingerprint."""

    inputs: dict[str, str]  # input name -> sha256 of its content
    config_hash: str
    code_version: str


@dataclass(frozen=True)
class Manifest:
    """The record of a finished stage output for one photo."""

    stage: str
    photo_key: str
    fingerprint: Fingerprint
    outputs: dict[str, FileRecord] = field(default_factory=dict)  # posix path relative to the stage folder
    config: dict[str, Any] = field(default_factory=dict)
    metrics: dict[str, Any] = field(default_factory=dict)
    wall_time_s: float = 0.0
    device: str = ""
    preset: str = ""
    plan: dict[str, Any] = field(default_factory=dict)  # the plan decisions this stage followed
    prior: str = ""  # which prior drove the stage, e.g. "proxy (weight-free)"
    notes: tuple[str, ...] = ()
    created_at: str = field(default_factory=utc_now)
    schema: int = SCHEMA

    @property
    def code_version(self) -> str:
        return self.fingerprint.code_version

    def to_json(self) -> str:
        """Strict JSON (indent 2, sorted keys); non-finite floats become "inf"/"-inf"/"nan"."""
        data = asdict(self)
        data["notes"] = list(self.notes)
        return json.dumps(_finite(data), indent=2, sort_keys=True, allow_nan=False) + "\n"

    @classmethod
    def from_json(cls, text: str) -> Manifest:
        """Parse a manifest; ValueError on malformed content or an unknown schema."""
        try:
            data = json.loads(text, parse_constant=_reject_constant)
        except json.JSONDecodeError as exc:
            raise ValueError(f"manifest is not valid JSON: {exc}") from exc
        try:
            return _parse(data)
        except (KeyError, TypeError, AttributeError) as exc:
            raise ValueError(f"malformed manifest: {exc!r}") from exc


def _reject_constant(name: str) -> Any:
    raise ValueError(f"manifest contains the non-standard JSON constant {name}")


def _finite(value: Any) -> Any:
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if isinstance(value, numbers.Integral):  # numpy integers from metric code serialise as ints
        return int(value)
    if isinstance(value, numbers.Real):
        value = float(value)
        if not math.isfinite(value):
            return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
        return value
    if isinstance(value, Mapping):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    return value


def _restore_metrics(value: Any) -> Any:
    # Only metrics are numeric by nature; a config or plan string "nan" stays a string.
    if isinstance(value, str) and value in _NON_FINITE:
        return _NON_FINITE[value]
    if isinstance(value, dict):
        return {k: _restore_metrics(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_restore_metrics(v) for v in value]
    return value


def _expect(value: Any, kind: type | tuple[type, ...], what: str) -> Any:
    if not isinstance(value, kind) or (isinstance(value, bool) and kind is not bool):  # bool is an int
        raise ValueError(f"manifest field {what} has the wrong type ({type(value).__name__})")
    return value


def _output_name(name: str) -> str:
    # The store opens stage_dir / name: an absolute or ".." name could point outside the stage.
    path = PurePosixPath(name)
    if not name or "\\" in name or path.is_absolute() or any(p in ("", ".", "..") for p in name.split("/")):
        raise ValueError(f"manifest output name {name!r} is not a plain relative path")
    return name


def _parse(data: Any) -> Manifest:
    _expect(data, dict, "<root>")
    if data.get("schema") != SCHEMA:
        raise ValueError(f"manifest schema {data.get('schema')!r} is not {SCHEMA}")
    known = {f.name for f in fields(Manifest)}
    if unknown := set(data) - known:
        raise ValueError(f"manifest has unknown fields {sorted(unknown)}")
    if missing := {"stage", "photo_key", "fingerprint"} - set(data):
        raise ValueError(f"manifest lacks fields {sorted(missing)}")

    fp = _expect(data["fingerprint"], dict, "fingerprint")
    inputs = _expect(fp["inputs"], dict, "fingerprint.inputs")
    for name, digest in inputs.items():
        _expect(digest, str, f"fingerprint.inputs.{name}")
    fingerprint = Fingerprint(
        inputs=dict(inputs),
        config_hash=_expect(fp["config_hash"], str, "fingerprint.config_hash"),
        code_version=_expect(fp["code_version"], str, "fingerprint.code_version"),
    )
    outputs = {}
    for name, rec in _expect(data.get("outputs", {}), dict, "outputs").items():
        _expect(rec, dict, f"outputs.{name}")
        outputs[_output_name(name)] = FileRecord(
            sha256=_expect(rec["sha256"], str, f"outputs.{name}.sha256"),
            size=_expect(rec["size"], int, f"outputs.{name}.size"),
        )
        if outputs[name].size < 0 or not _SHA256.fullmatch(outputs[name].sha256):
            raise ValueError(f"manifest output record for {name!r} is malformed")
    wall = data.get("wall_time_s", 0.0)
    wall = _NON_FINITE[wall] if isinstance(wall, str) and wall in _NON_FINITE else wall
    notes = _expect(data.get("notes", []), list, "notes")
    for note in notes:
        _expect(note, str, "notes[]")
    return Manifest(
        stage=_expect(data["stage"], str, "stage"),
        photo_key=_expect(data["photo_key"], str, "photo_key"),
        fingerprint=fingerprint,
        outputs=outputs,
        config=_expect(data.get("config", {}), dict, "config"),
        metrics=_restore_metrics(_expect(data.get("metrics", {}), dict, "metrics")),
        wall_time_s=float(_expect(wall, (int, float), "wall_time_s")),
        device=_expect(data.get("device", ""), str, "device"),
        preset=_expect(data.get("preset", ""), str, "preset"),
        plan=_expect(data.get("plan", {}), dict, "plan"),
        prior=_expect(data.get("prior", ""), str, "prior"),
        notes=tuple(notes),
        created_at=_expect(data.get("created_at", ""), str, "created_at"),
        schema=SCHEMA,
    )
