"""Content hashes for stage fingerprints: files, bytes, and configurations.

``config_hash`` hashes a canonical JSON form, not ``hash()`` or ``repr()`` of the object, so the
value is stable across processes, Python versions and machines (no hash randomisation, no memory
addresses, no dict-order dependence) and can be stored in manifests and compared on a later run.
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import json
import math
import numbers
from collections.abc import Mapping
from pathlib import PurePath
from typing import Any

_CHUNK = 1 << 20


def file_sha256(path: str | PurePath) -> str:
    """Hex sha256 of a file, read in 1 MiB chunks so big outputs never sit in memory whole."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(_CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


def bytes_sha256(data: bytes) -> str:
    """Hex sha256 of ``data``."""
    return hashlib.sha256(data).hexdigest()


def _float(value: float) -> float | str:
    # Strict JSON has no inf/nan; their repr keeps them distinct from every finite value.
    return value if math.isfinite(value) else repr(value)


def canonical(value: Any) -> Any:
    """``value`` as plain JSON types, the same for equal configurations in any process."""
    if isinstance(value, enum.Enum):  # first: IntEnum/StrEnum members are ints/strs too
        return str(value)
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, numbers.Integral):  # numpy integers included
        return int(value)
    if isinstance(value, numbers.Real):
        return _float(float(value))
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return canonical(dataclasses.asdict(value))
    if isinstance(value, Mapping):
        return {str(k): canonical(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [canonical(v) for v in value]
    if isinstance(value, (set, frozenset)):
        items = [canonical(v) for v in value]
        return sorted(items, key=lambda v: json.dumps(v, sort_keys=True))
    if isinstance(value, PurePath):
        return str(value)
    return str(value)


def canonical_json(value: Any) -> str:
    """Compact canonical JSON: sorted keys, no whitespace, ASCII only, floats by repr."""
    return json.dumps(canonical(value), sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)


def config_hash(config: Any) -> str:
    """Hex sha256 of the canonical JSON of ``config`` (a dataclass, mapping, or plain value).

    Stable across processes and machines; 0.1 hashes as 0.1 (Python's shortest repr), tuples hash as
    lists, Paths as strings, enums and other objects by ``str``.
    """
    return bytes_sha256(canonical_json(config).encode("ascii"))
