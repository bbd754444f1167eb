"""Photo keys: the folder name under the store root that holds everything derived from one photo.

A key must be safe on every filesystem the store may live on (no separators, no "..", no leading
dot or dash, plain ASCII) and stable: it depends only on the photo's own name, never on which other
photos exist, so a rerun finds the same folder. Lossy mappings (unicode, spaces, sub-folders) get a
short hash of the original name so that distinct names keep distinct keys.
"""

from __future__ import annotations

import hashlib
import re
import unicodedata
from collections.abc import Iterable

MAX_KEY_LENGTH = 128
_STEM_LENGTH = 96  # leaves room for the "-<hash>" suffixes within MAX_KEY_LENGTH
_FALLBACK = "photo"
_COMPONENT_JOIN = "__"

_SAFE_CHARS = re.compile(r"[A-Za-z0-9._-]+")
_UNSAFE_CHAR = re.compile(r"[^A-Za-z0-9._-]")
_UNDERSCORES = re.compile(r"_+")
_DOTS = re.compile(r"\.+")
_EDGE = "._-"


class UnsafeKeyError(ValueError):
    """A key (or a path built from it) that could escape or confuse the store layout."""


def _sha256_hex(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8", "surrogatepass")).hexdigest()


def _ascii(text: str) -> str:
    # NFKC first folds compatibility forms (full-width letters, ligatures); NFKD then splits accents
    # off their letters so dropping non-ASCII keeps "cafe" from "café".
    text = unicodedata.normalize("NFKC", text)
    return unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode("ascii")


def _clean_component(part: str) -> str:
    part = _UNSAFE_CHAR.sub("_", _ascii(part))
    part = _UNDERSCORES.sub("_", part)
    part = _DOTS.sub(".", part)
    return part.strip(_EDGE)


def photo_key(name: str) -> str:
    """The store key for a photo file name, or a path relative to a scanned folder.

    Lossless names (already safe) are returned unchanged, extension included ("mug.jpg"); any other
    name gets "-" + 8 hex chars of sha256(name) appended so distinct originals stay distinct.
    """
    # Components are cleaned one by one so the "__" joiner survives the collapse of "_" runs.
    parts = [_clean_component(p) for p in re.split(r"[/\\]", name)]
    key = _COMPONENT_JOIN.join(p for p in parts if p)
    key = key[:_STEM_LENGTH].strip(_EDGE) or _FALLBACK
    if key != name:
        key = f"{key}-{_sha256_hex(name)[:8]}"
    return key


def key_problem(key: str) -> str | None:
    """Why ``key`` is unsafe, or None when it is safe."""
    if not isinstance(key, str):
        return f"not a string ({type(key).__name__})"
    if not key:
        return "empty"
    if len(key) > MAX_KEY_LENGTH:
        return f"longer than {MAX_KEY_LENGTH} characters"
    if not _SAFE_CHARS.fullmatch(key):
        return "characters outside [A-Za-z0-9._-]"
    if ".." in key:
        return 'contains ".."'
    if key[0] in ".-":
        return f'starts with "{key[0]}"'
    return None


def is_safe_key(key: str) -> bool:
    """True when ``key`` can be used as a folder name under the store root."""
    return key_problem(key) is None


def check_key(key: str) -> str:
    """Return ``key`` unchanged, or raise UnsafeKeyError naming it and the reason."""
    problem = key_problem(key)
    if problem is not None:
        raise UnsafeKeyError(f"unsafe photo key {key!r}: {problem}")
    return key


def _with_suffix(key: str, name: str, digits: int) -> str:
    suffix = f"-{_sha256_hex(name)[:digits]}"
    return key[: MAX_KEY_LENGTH - len(suffix)] + suffix


def assign_keys(names: Iterable[str]) -> dict[str, str]:
    """Keys for a set of names, unique even on case-insensitive filesystems.

    Names whose keys are equal ignoring case form a group; sorted by original name, the first keeps
    its key and the others get "-" + 12 hex chars of sha256(name) appended. Deterministic and
    independent of input order.
    """
    base = {name: photo_key(name) for name in sorted(set(names))}
    groups: dict[str, list[str]] = {}
    for name, key in base.items():  # sorted insertion: each group is in original-name order
        groups.setdefault(key.lower(), []).append(name)

    result = {members[0]: base[members[0]] for members in groups.values()}
    taken = set(groups)
    for members in groups.values():
        for name in members[1:]:
            # Longer hashes only when a suffixed key happens to equal another photo's key.
            for digits in (12, 16, 24, 32, 64):
                key = _with_suffix(base[name], name, digits)
                if key.lower() not in taken:
                    break
            else:  # pragma: no cover - needs a sha256 collision
                raise UnsafeKeyError(f"cannot give {name!r} a unique key")
            result[name] = check_key(key)
            taken.add(key.lower())
    return result
