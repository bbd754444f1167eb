"""Typed configuration trees: frozen dataclasses ↔ plain dicts, and ``key.sub=value`` overrides.

There is one way to configure a run: a ``PipelineConfig`` (a tree of frozen dataclasses) from a
preset, with overrides addressed by dotted paths (``--set nerf.loop.steps=200``). Values are
parsed and checked against the field's annotation, so a typo or a wrong type fails before any
work starts, naming the valid keys.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import inspect
import itertools
import json
import re
import textwrap
import types
import typing
from collections.abc import Iterable
from typing import Any, TypeVar

T = TypeVar("T")


class ConfigError(ValueError):
    """An override names no field, or its value does not fit the field's type."""


def to_dict(config: Any) -> Any:
    """Plain JSON-ready data (tuples become lists)."""
    if dataclasses.is_dataclass(config) and not isinstance(config, type):
        return {f.name: to_dict(getattr(config, f.name)) for f in dataclasses.fields(config)}
    if isinstance(config, (list, tuple)):
        return [to_dict(v) for v in config]
    if isinstance(config, dict):
        return {str(k): to_dict(v) for k, v in config.items()}
    return config


def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _coerce(value: Any, hint: Any, where: str) -> Any:
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if hint is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in (a for a in args if a is not type(None)):
            try:
                return _coerce(value, arg, where)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(f"{where}: {value!r} fits none of {hint}: {'; '.join(errors)}")
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"{where}: {value!r} is not one of {list(args)}")
        return value
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], where) for v in value)
        if len(args) != len(value):
            raise ConfigError(f"{where}: expected {len(args)} values, got {len(value)}")
        return tuple(_coerce(v, a, where) for v, a in zip(value, args, strict=True))
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping, got {value!r}")
        return dict(value)
    if dataclasses.is_dataclass(hint):
        if isinstance(value, hint):
            return value
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping for {hint.__name__}, got {value!r}")
        return from_dict(hint, value, where)
    if hint is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{where}: expected true/false, got {value!r}")
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    return value


def from_dict(cls: type[T], data: dict[str, Any], where: str = "") -> T:
    """Rebuild a dataclass tree from ``to_dict`` output (missing keys keep their defaults)."""
    hints = _hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(f"{where or cls.__name__}: unknown keys {unknown}; valid: {sorted(names)}")
    kwargs = {k: _coerce(v, hints[k], f"{where}.{k}".lstrip(".")) for k, v in data.items()}
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where or cls.__name__}: {exc}") from exc


def _parse(text: str) -> Any:
    """JSON when it parses (numbers, true/false, null, lists), else the raw string."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def override(config: T, path: str, value: Any) -> T:
    """A copy of ``config`` with the field at dotted ``path`` set to ``value`` (checked)."""
    head, _, rest = path.partition(".")
    fields = {f.name: f for f in dataclasses.fields(config)}
    if head not in fields:
        raise ConfigError(f"{path}: no field {head!r} in {type(config).__name__}; valid: {sorted(fields)}")
    current = getattr(config, head)
    if rest:
        if not dataclasses.is_dataclass(current):
            raise ConfigError(f"{path}: {head!r} is a value, not a group of settings")
        try:
            new = override(current, rest, value)
        except ConfigError as exc:
            # The nested call knows only the path below ``head``: the message names the whole key.
            raise ConfigError(f"{head}.{exc}") from exc
    else:
        new = _coerce(value, _hints(type(config))[head], path)
    try:
        return dataclasses.replace(config, **{head: new})
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{path}={value!r}: {exc}") from exc


def apply_overrides(config: T, assignments: Iterable[str]) -> T:
    """Apply ``key.sub=value`` strings in order; values are JSON or bare strings. A ``*`` segment
    matches any one name (``*.loop.early_stop=false``: every stage's loop)."""
    for item in assignments:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ConfigError(f"{item!r}: an override is key=value, e.g. nerf.loop.steps=200")
        for path in _expand(config, key):
            config = override(config, path, _parse(text.strip()))
    return config


def _expand(config: Any, key: str) -> list[str]:
    if "*" not in key:
        return [key]
    pattern = key.split(".")
    paths = [k for k in flat_keys(config) if len(parts := k.split(".")) == len(pattern)
             and all(p in ("*", name) for p, name in zip(pattern, parts, strict=True))]
    if not paths:
        raise ConfigError(f"{key}: matches no setting (a * stands for one name, e.g. *.loop.steps)")
    return paths


def flat_keys(config: Any, prefix: str = "") -> list[str]:
    """Every overridable dotted path (for help and error messages)."""
    return [key for key, _, _ in describe_keys(config, prefix)]


_RST_LITERAL = re.compile(r"``([^`]+)``")


@functools.cache
def field_docs(cls: type) -> dict[str, str]:
    """Each field's one-line doc: the string literal right after the field in the class body (an
    attribute docstring, which IDEs show too), whitespace folded and reStructuredText literals
    (````x````) shown as plain ``x`` on the command line (``--list-keys``). Fields a class inherits
    keep their base class's docs (a generated class has no source of its own)."""
    docs = {k: v for base in reversed(cls.__mro__[1:]) if dataclasses.is_dataclass(base)
            for k, v in field_docs(base).items()}
    try:
        source = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):
        return docs
    body = ast.parse(source).body[0].body  # type: ignore[attr-defined]
    for node, after in itertools.pairwise(body):
        if (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and isinstance(after, ast.Expr)
                and isinstance(after.value, ast.Constant) and isinstance(after.value.value, str)):
            docs[node.target.id] = _RST_LITERAL.sub(r"\1", " ".join(after.value.value.split()))
    return docs


def describe_keys(config: Any, prefix: str = "") -> list[tuple[str, Any, str]]:
    """Every overridable dotted path with its current value and its field's doc (``--list-keys``)."""
    out: list[tuple[str, Any, str]] = []
    docs = field_docs(type(config))
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        path = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value):
            out += describe_keys(value, path + ".")
        else:
            out.append((path, value, docs.get(f.name, "")))
    return out
