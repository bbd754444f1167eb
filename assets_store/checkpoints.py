"""Stage checkpoints: resumable training state that survives a kill at any instant.

File ``step-{step:09d}.ckpt`` = MAGIC + payload length (8 bytes, little-endian) + sha256 of the
payload (32 bytes) + payload (``torch.save`` of the state). Files are written atomically, and on
load every byte is checked, so a truncated, bit-flipped or empty file is detected, set aside as
``<name>.corrupt`` (kept for inspection, never tried again) and the next older checkpoint is used.

A state holding NaN/Inf in a float tensor is refused at save time: resuming from a diverged state
would only reproduce the divergence, and the older finite checkpoints stay available.
"""

from __future__ import annotations

import hashlib
import io
import os
import re
import struct
import time
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from assets_store.atomic import HOST, atomic_write_bytes
from assets_store.fsutil import fsync_dir, pid_alive

MAGIC = b"M3DCKPT1"
_LENGTH = struct.Struct("<Q")
HEADER_SIZE = len(MAGIC) + _LENGTH.size + 32
_STEP_FILE = re.compile(r"step-(\d{9,})\.ckpt")
# atomic_write's temporaries: ".<name>.<host>.<pid>.tmp" (".<name>.<pid>.tmp" before hosts were named)
_TEMP_FILE = re.compile(r"\.step-\d{9,}\.ckpt\.(?:(?P<host>[A-Za-z0-9-]+)\.)?(?P<pid>\d+)\.tmp")
_ABANDONED_S = 3600.0  # a temporary of another host this old was left by a killed writer (a save takes seconds)


class CheckpointError(RuntimeError):
    """A checkpoint could not be written or read."""


class NonFiniteStateError(CheckpointError):
    """The state to save holds NaN or Inf in a floating-point tensor."""


def _find_non_finite(value: Any, path: str) -> str | None:
    if isinstance(value, torch.Tensor):
        if (value.is_floating_point() or value.is_complex()) and not bool(torch.isfinite(value).all()):
            return path or "<state>"
        return None
    if isinstance(value, Mapping):
        items = value.items()
    elif isinstance(value, (list, tuple)):
        items = enumerate(value)
    else:
        return None
    for key, item in items:
        found = _find_non_finite(item, f"{path}.{key}" if path else str(key))
        if found is not None:
            return found
    return None


def check_finite(state: Mapping[str, Any]) -> None:
    """Raise NonFiniteStateError naming the key path (e.g. "optimizers.nerf.state.3.exp_avg") of the
    first floating-point tensor holding NaN or Inf."""
    found = _find_non_finite(state, "")
    if found is not None:
        raise NonFiniteStateError(f"refusing to checkpoint a non-finite state: NaN/Inf in {found}")


def encode(state: Mapping[str, Any]) -> bytes:
    """The checkpoint file's bytes for ``state``."""
    buffer = io.BytesIO()
    torch.save(dict(state), buffer)
    payload = buffer.getvalue()
    return MAGIC + _LENGTH.pack(len(payload)) + hashlib.sha256(payload).digest() + payload


def decode(data: bytes) -> dict[str, Any]:
    """The state in a checkpoint file's bytes; CheckpointError when anything does not check out."""
    if len(data) < HEADER_SIZE:
        raise CheckpointError(f"{len(data)} bytes, shorter than the {HEADER_SIZE}-byte header")
    if data[: len(MAGIC)] != MAGIC:
        raise CheckpointError("wrong magic")
    (length,) = _LENGTH.unpack_from(data, len(MAGIC))
    payload = memoryview(data)[HEADER_SIZE:]  # a view: checkpoints can be large, avoid a copy
    if len(payload) != length:
        raise CheckpointError(f"payload is {len(payload)} bytes, header says {length}")
    if hashlib.sha256(payload).digest() != data[len(MAGIC) + _LENGTH.size : HEADER_SIZE]:
        raise CheckpointError("payload sha256 does not match")
    try:
        state = torch.load(io.BytesIO(payload), map_location="cpu", weights_only=True)
    except Exception as exc:  # the unpickler raises many types; a digest-valid file should never get here
        raise CheckpointError(f"torch.load failed: {exc!r}") from exc
    if not isinstance(state, dict):
        raise CheckpointError(f"payload is a {type(state).__name__}, not a dict")
    return state


def _looks_complete(path: Path) -> bool:
    # Header against file size only: cheap enough to run on every save without re-reading payloads.
    try:
        with open(path, "rb") as fh:
            header = fh.read(HEADER_SIZE)
            size = os.fstat(fh.fileno()).st_size
    except OSError:
        return False
    if len(header) < HEADER_SIZE or header[: len(MAGIC)] != MAGIC:
        return False
    return _LENGTH.unpack_from(header, len(MAGIC))[0] == size - HEADER_SIZE


class Checkpoints:
    """The checkpoints of one running stage, in ``directory``; the ``keep`` newest are kept."""

    def __init__(self, directory: Path, keep: int = 2) -> None:
        if keep < 1:
            raise ValueError(f"keep must be at least 1, got {keep}")
        self.directory = Path(directory)
        self.keep = keep

    def path_for(self, step: int) -> Path:
        return self.directory / f"step-{step:09d}.ckpt"

    def steps(self) -> list[int]:
        """Steps with a checkpoint file (by name; contents are checked on load), ascending."""
        if not self.directory.is_dir():
            return []
        found = (_STEP_FILE.fullmatch(p.name) for p in self.directory.iterdir())
        return sorted(int(m[1]) for m in found if m is not None)

    def save(self, step: int, state: Mapping[str, Any]) -> Path:
        """Write ``state`` as the checkpoint of ``step`` atomically, then prune old checkpoints.

        Raises NonFiniteStateError (and writes nothing) when a float tensor holds NaN/Inf.
        """
        if isinstance(step, bool) or not isinstance(step, int) or step < 0:
            raise ValueError(f"step must be a non-negative int, got {step!r}")
        check_finite(state)
        path = self.path_for(step)
        atomic_write_bytes(path, encode(state))
        fsync_dir(self.directory)
        self._prune(keep_path=path)
        return path

    def load_latest(self) -> tuple[int, dict[str, Any]] | None:
        """The newest checkpoint that checks out, as (step, state); None when there is none.

        Bad files are skipped with a RuntimeWarning and renamed to ``<name>.corrupt``.
        """
        for step in reversed(self.steps()):
            path = self.path_for(step)
            try:
                data = path.read_bytes()
            except FileNotFoundError:  # pruned by a concurrent save
                continue
            try:
                return step, decode(data)
            except CheckpointError as exc:
                self._set_aside(path, str(exc))
        return None

    def clear(self) -> None:
        """Remove every checkpoint file, temporary and .corrupt file, and the folder if then empty."""
        if not self.directory.is_dir():
            return
        for path in self.directory.iterdir():
            if path.is_file() and (
                _STEP_FILE.fullmatch(path.name)
                or _TEMP_FILE.fullmatch(path.name)
                or path.name.endswith(".ckpt.corrupt")
            ):
                path.unlink(missing_ok=True)
        try:
            self.directory.rmdir()
        except OSError:
            pass

    def _set_aside(self, path: Path, why: str) -> None:
        corrupt = path.with_name(path.name + ".corrupt")
        warnings.warn(f"skipping corrupt checkpoint {path} ({why}); renamed to {corrupt.name}", RuntimeWarning,
                      stacklevel=3)
        try:
            os.replace(path, corrupt)
        except FileNotFoundError:
            pass

    def _prune(self, keep_path: Path) -> None:
        kept = 0
        for step in reversed(self.steps()):
            path = self.path_for(step)
            if path == keep_path:
                kept += 1
            elif kept < self.keep and _looks_complete(path):
                kept += 1
            elif kept < self.keep:
                self._set_aside(path, "header does not match the file size")
            else:
                path.unlink(missing_ok=True)
        # Temporaries of killed writers would otherwise pile up beside the checkpoints. A process id
        # is judged only on its own host; another host's temporary is left alone until it is old.
        now = time.time()
        for path in self.directory.iterdir():
            match = _TEMP_FILE.fullmatch(path.name)
            if match is None:
                continue
            here = match["host"] in (None, HOST)
            try:
                old = now - path.stat().st_mtime > _ABANDONED_S
            except FileNotFoundError:
                continue
            if (here and not pid_alive(int(match["pid"]))) or old:
                path.unlink(missing_ok=True)

