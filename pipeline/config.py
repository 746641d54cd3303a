"""Strict construction of frozen config dataclasses from plain mappings.

Reading YAML is the services' job; this module only turns an already-parsed mapping into
typed, validated dataclasses. Unknown keys, missing required keys and wrong types raise
`ConfigError` naming the source, the dotted key and the expected type.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Mapping
from typing import Any, Literal, TypeVar, get_args, get_origin, get_type_hints

T = TypeVar("T")


class ConfigError(ValueError):
    """A config value is unknown, missing or of the wrong type."""

    def __init__(self, source: str, key: str, message: str) -> None:
        self.source = source
        self.key = key
        super().__init__(f"{source}: key '{key}': {message}")


def from_mapping(cls: type[T], data: Any, *, source: str = "<config>", key: str = "") -> T:
    """Build dataclass `cls` from `data`, rejecting unknown keys and wrong types.

    Args:
        cls: A (frozen) dataclass type whose fields carry type annotations.
        data: The parsed mapping (e.g. from YAML). `None` means "all defaults".
        source: Where the data came from (a file name), used in error messages.
        key: Dotted prefix of `data` inside the source, used in error messages.

    Returns:
        An instance of `cls`. Validation in its `__post_init__` has run; a `ValueError`
        raised there is re-raised as a `ConfigError` naming `key`.
    """
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise ConfigError(source, key or "<root>", f"expected a mapping for {cls.__name__}, got {_kind(data)}")
    hints = get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}  # type: ignore[arg-type]
    unknown = sorted(str(k) for k in data if k not in fields)
    if unknown:
        where = _join(key, unknown[0])
        raise ConfigError(source, where, f"unknown key (known keys of {cls.__name__}: {', '.join(sorted(fields))})")
    kwargs: dict[str, Any] = {}
    for name, field in fields.items():
        sub_key = _join(key, name)
        if name in data:
            kwargs[name] = _convert(hints[name], data[name], source=source, key=sub_key)
        elif field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING:
            raise ConfigError(source, sub_key, f"required key is missing (expected {_type_name(hints[name])})")
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (ValueError, TypeError) as exc:
        raise ConfigError(source, key or "<root>", str(exc)) from exc


def _convert(tp: Any, value: Any, *, source: str, key: str) -> Any:
    origin = get_origin(tp)
    args = get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert(arg, value, source=source, key=key)
            except ConfigError as exc:
                errors.append(exc)
        raise ConfigError(source, key, f"expected {_type_name(tp)}, got {_kind(value)}")
    if origin is Literal:
        if value not in args:
            raise ConfigError(source, key, f"expected one of {list(args)}, got {value!r}")
        return value
    if dataclasses.is_dataclass(tp):
        return from_mapping(tp, value, source=source, key=key)  # type: ignore[arg-type]
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(source, key, f"expected a list ({_type_name(tp)}), got {_kind(value)}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, source=source, key=f"{key}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(source, key, f"expected a list of {len(args)} items, got {len(value)}")
        return tuple(_convert(a, v, source=source, key=f"{key}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
    if origin in (dict, Mapping) or tp is dict:
        if not isinstance(value, Mapping):
            raise ConfigError(source, key, f"expected a mapping ({_type_name(tp)}), got {_kind(value)}")
        key_tp, val_tp = args if args else (Any, Any)
        return {
            _convert(key_tp, k, source=source, key=f"{key}.{k}"): _convert(val_tp, v, source=source, key=f"{key}.{k}")
            for k, v in value.items()
        }
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(source, key, f"expected bool, got {_kind(value)}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(source, key, f"expected int, got {_kind(value)}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(source, key, f"expected float, got {_kind(value)}")
        if not math.isfinite(value):
            raise ConfigError(source, key, f"expected a finite float, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(source, key, f"expected str, got {_kind(value)}")
        return value
    raise TypeError(f"config type {tp!r} at '{key}' is not supported by the loader")


def _join(prefix: str, name: str) -> str:
    return f"{prefix}.{name}" if prefix else name


def _kind(value: Any) -> str:
    return f"{type(value).__name__} ({value!r})" if not isinstance(value, (dict, list)) else type(value).__name__


def _type_name(tp: Any) -> str:
    if isinstance(tp, type):
        return tp.__name__
    return str(tp).replace("typing.", "")


def require(condition: bool, message: str) -> None:
    """Raise `ValueError(message)` unless `condition`; for `__post_init__` validation."""
    if not condition:
        raise ValueError(message)
