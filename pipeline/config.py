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
        self.detail = message
        super().__init__(f"{source}: key '{key}': {message}")


class _Reported(ConfigError):
    """Errors below this key are already in the caller's list: give up on this value only."""


def from_mapping(cls: type[T], data: Any, *, source: str = "<config>", key: str = "",
                 errors: list[ConfigError] | None = None) -> T:
    """Build dataclass `cls` from `data`, rejecting unknown keys and wrong types.

    Args:
        cls: A (frozen) dataclass type whose fields carry type annotations.
        data: The parsed mapping (e.g. from YAML). `None` means "all defaults".
        source: Where the data came from (a file name), used in error messages.
        key: Dotted prefix of `data` inside the source, used in error messages.
        errors: Collect every error here instead of raising the first: each bad key is
            reported and the rest still checked. A section with a bad key skips its own
            cross-key checks (they would only repeat the fault); then a ConfigError is
            raised after all, once everything was checked.

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
    failed = False

    def fail(error: ConfigError) -> None:
        nonlocal failed
        if errors is None:
            raise error
        failed = True
        if not isinstance(error, _Reported):
            errors.append(error)

    for unknown in sorted(str(k) for k in data if k not in fields):
        fail(ConfigError(source, _join(key, unknown),
                         f"unknown key (known keys of {cls.__name__}: {', '.join(sorted(fields))})"))
    kwargs: dict[str, Any] = {}
    for name, field in fields.items():
        sub_key = _join(key, name)
        try:
            if name in data:
                kwargs[name] = _convert(hints[name], data[name], source=source, key=sub_key, errors=errors)
            elif field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING:
                fail(ConfigError(source, sub_key, f"required key is missing (expected {_type_name(hints[name])})"))
        except ConfigError as exc:
            fail(exc)
    if failed:
        raise _Reported(source, key or "<root>", "has errors")
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (ValueError, TypeError) as exc:
        raise ConfigError(source, key or "<root>", str(exc)) from exc


def collect_errors(cls: type[T], data: Any, *, source: str = "<config>") -> tuple[T | None, list[ConfigError]]:
    """`from_mapping` that reports every error: (the config, []) or (None, every error found)."""
    errors: list[ConfigError] = []
    try:
        return from_mapping(cls, data, source=source, errors=errors), []
    except _Reported:
        return None, errors
    except ConfigError as exc:
        return None, [*errors, exc]


def _convert(tp: Any, value: Any, *, source: str, key: str, errors: list[ConfigError] | None = None) -> Any:
    origin = get_origin(tp)
    args = get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        choices = [arg for arg in args if arg is not type(None)]
        if errors is not None and len(choices) == 1 and dataclasses.is_dataclass(choices[0]):
            return _convert(choices[0], value, source=source, key=key, errors=errors)  # a section: check its every key
        for arg in choices:
            try:
                return _convert(arg, value, source=source, key=key)
            except ConfigError:
                pass
        raise ConfigError(source, key, f"expected {_type_name(tp)}, got {_kind(value)}")
    if origin is Literal:
        if value not in args:
            raise ConfigError(source, key, f"expected one of {list(args)}, got {value!r}")
        return value
    if dataclasses.is_dataclass(tp):
        return from_mapping(tp, value, source=source, key=key, errors=errors)  # type: ignore[arg-type]
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(source, key, f"expected a list ({_type_name(tp)}), got {_kind(value)}")
        if len(args) == 2 and args[1] is Ellipsis:
            if errors is None:
                return tuple(_convert(args[0], v, source=source, key=f"{key}[{i}]") for i, v in enumerate(value))
            items, failed = [], False
            for i, v in enumerate(value):  # every item is checked, also after a bad one
                try:
                    items.append(_convert(args[0], v, source=source, key=f"{key}[{i}]", errors=errors))
                except _Reported:
                    failed = True
                except ConfigError as exc:
                    errors.append(exc)
                    failed = True
            if failed:
                raise _Reported(source, key, "has errors")
            return tuple(items)
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
