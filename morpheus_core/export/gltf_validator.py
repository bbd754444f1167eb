"""The Khronos glTF-Validator, run through Node.js, as a Python check on exported GLB / glTF files.

Exports are only known to load when the reference validator says so: trimesh and our own writer
(``morpheus_core.export.web_glb``) can both produce files that parse in one viewer and fail in
another. The validator is the npm package ``gltf-validator`` (compiled from Dart to JS), pinned in
``tools/web/package.json`` and installed by ``make web-tools`` (``npm ci --prefix tools/web``); the
runner ``tools/web/validate_gltf.mjs`` reads the file, calls ``validator.validateBytes`` and prints
the report as JSON, which ``validate_gltf`` condenses into a ``GltfValidation``.

Where things are looked up (first hit wins):

* the tools folder (the one holding ``node_modules/gltf-validator``): the ``tools_dir`` argument,
  else ``morpheus_core.export.web_tools.web_tools_dir()`` (``MORPHEUS_WEB_TOOLS``, else the repository's
  ``tools/web``);
* the runner script: always ``tools/web/validate_gltf.mjs`` of this repository (it is versioned
  with this module); it loads the validator from the tools folder above;
* ``node``: the ``node`` argument, else ``MORPHEUS_NODE``, else ``node`` on ``PATH``.

Note: the validator (2.0.0-dev.3.10) does not know ``EXT_meshopt_compression``; it reports it as
an info (UNSUPPORTED_EXTENSION) and cannot check the data of compressed buffer views.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from morpheus_core.export.web_tools import REPO_WEB_TOOLS, WEB_TOOLS_ENV, web_tools_dir

# The runner is versioned with this module, so it is always the repository's own.
RUNNER = REPO_WEB_TOOLS / "validate_gltf.mjs"
TOOLS_ENV = WEB_TOOLS_ENV
NODE_ENV = "MORPHEUS_NODE"

_SEVERITIES = {0: "error", 1: "warning", 2: "info", 3: "hint"}


class ValidatorUnavailable(RuntimeError):
    """Node.js, the runner script or the gltf-validator package is missing; the message says the fix."""


class ValidatorFailed(RuntimeError):
    """The validator ran but did not produce a report (crashed, timed out, printed no JSON)."""


@dataclass(frozen=True)
class ValidationMessage:
    """One issue of the report."""

    code: str
    """The validator's issue code, e.g. ``ACCESSOR_INDEX_OOB``."""
    message: str
    pointer: str | None
    """JSON pointer into the asset (``/accessors/0``), or ``@<byte offset>`` for GLB-level issues."""
    severity: str
    """``error``, ``warning``, ``info`` or ``hint``."""


@dataclass(frozen=True)
class GltfValidation:
    """The condensed report: issue counts, the error and warning messages, the validator version."""

    errors: int
    warnings: int
    infos: int
    hints: int
    messages: tuple[ValidationMessage, ...]
    """Errors and warnings (infos and hints are only counted)."""
    validator_version: str
    info_codes: tuple[str, ...] = ()
    """Distinct codes of the infos (e.g. UNSUPPORTED_EXTENSION), for a reader who wonders what they were."""

    @property
    def ok(self) -> bool:
        return self.errors == 0

    @property
    def error_messages(self) -> tuple[ValidationMessage, ...]:
        return tuple(m for m in self.messages if m.severity == "error")

    @property
    def warning_messages(self) -> tuple[ValidationMessage, ...]:
        return tuple(m for m in self.messages if m.severity == "warning")


def _tools_dir(tools_dir: Path | str | None) -> Path:
    return Path(tools_dir) if tools_dir is not None else web_tools_dir()


def _node(node: str | None) -> str | None:
    candidate = node or os.environ.get(NODE_ENV) or "node"
    if os.sep in candidate:
        return candidate if os.access(candidate, os.X_OK) else None
    return shutil.which(candidate)


def validator_available(tools_dir: Path | str | None = None, node: str | None = None) -> str | None:
    """None when ``validate_gltf`` can run, else a message naming what is missing and the fix."""
    node_path = _node(node)
    if node_path is None:
        wanted = node or os.environ.get(NODE_ENV) or "node"
        return (f"Node.js ({wanted!r}) was not found: install Node.js ≥ 18 (e.g. `apt-get install nodejs`) "
                f"or point {NODE_ENV} at the node executable")
    if not RUNNER.is_file():
        return f"the validator runner {RUNNER} is missing (it is part of this repository: restore it)"
    tools = _tools_dir(tools_dir)
    package = tools / "node_modules" / "gltf-validator" / "package.json"
    if not package.is_file():
        return (f"the npm package gltf-validator is not installed in {tools}: run `make web-tools` "
                f"(i.e. `npm ci --prefix tools/web`), or set {TOOLS_ENV} to a folder that has it in node_modules")
    return None


def _message(raw: dict[str, Any]) -> ValidationMessage:
    pointer = raw.get("pointer")
    if pointer is None and raw.get("offset") is not None:
        pointer = f"@{raw['offset']}"
    return ValidationMessage(code=str(raw.get("code", "")), message=str(raw.get("message", "")), pointer=pointer,
                             severity=_SEVERITIES.get(int(raw.get("severity", 0)), "error"))


def parse_report(report: dict[str, Any]) -> GltfValidation:
    """A ``GltfValidation`` from the validator's report object (its JSON form)."""
    issues = report.get("issues", {})
    messages = [_message(m) for m in issues.get("messages", [])]
    return GltfValidation(
        errors=int(issues.get("numErrors", 0)), warnings=int(issues.get("numWarnings", 0)),
        infos=int(issues.get("numInfos", 0)), hints=int(issues.get("numHints", 0)),
        messages=tuple(m for m in messages if m.severity in ("error", "warning")),
        validator_version=str(report.get("validatorVersion", "unknown")),
        info_codes=tuple(sorted({m.code for m in messages if m.severity == "info"})),
    )


def validate_gltf(path: Path | str, *, tools_dir: Path | str | None = None, node: str | None = None,
                  timeout_s: float = 120.0) -> GltfValidation:
    """Validate the .glb / .gltf at ``path`` (a .gltf's external files are read beside it).

    ``tools_dir`` / ``node`` override the lookups of the module docstring. Raises
    ``ValidatorUnavailable`` without the tools, FileNotFoundError for a missing file and
    ``ValidatorFailed`` when no report comes back. An invalid asset is *not* an exception: look at
    ``errors`` (or ``ok``)."""
    missing = validator_available(tools_dir, node)
    if missing is not None:
        raise ValidatorUnavailable(missing)
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no glTF file at {path}")
    node_path = _node(node)
    if node_path is None:  # validator_available said yes a moment ago; the PATH may have changed since
        raise ValidatorUnavailable("Node.js disappeared from PATH")
    cmd = [node_path, str(RUNNER), str(path.resolve()), "--modules", str(_tools_dir(tools_dir).resolve())]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, check=False)
    except subprocess.TimeoutExpired as exc:
        raise ValidatorFailed(f"glTF validator timed out after {timeout_s:.0f} s on {path}") from exc
    if proc.returncode != 0:
        raise ValidatorFailed(f"glTF validator exited with {proc.returncode} on {path}: {proc.stderr.strip()}")
    try:
        report = json.loads(proc.stdout)
    except json.JSONDecodeError as exc:
        raise ValidatorFailed(f"glTF validator printed no JSON report for {path}: {proc.stdout[:200]!r}") from exc
    return parse_report(report)
