"""Wire codec: msgpack maps with a schema version, arrays as `{dtype, shape, data}`, errors.

Every payload is a msgpack map with snake_case string keys, a schema version `v`, and a
`stamp` (float Unix seconds) where it describes a moment. Arrays travel as maps
`{dtype: "<f4", shape: [N, 3], data: <bytes>}`, little-endian and C order, so any language
decodes them without this package. The messages themselves are in `messages.py`;
`docs/protocol.md` is the human-readable spec of both.

Decoding is strict: unknown keys, missing keys, wrong types, wrong shapes and non-finite
numbers (where a field forbids them) raise `ProtocolError` carrying an `ErrorCode`, which
services turn into a structured error reply. It is also bounded: nesting depth, collection
lengths and array sizes are checked before anything is built from them, so no payload makes
a decoder allocate more than the payload itself or raise anything but `ProtocolError`.
"""
from __future__ import annotations

import dataclasses
import enum
import functools
import math
import types
import typing
from dataclasses import dataclass, field
from typing import Any, ClassVar, TypeVar, get_type_hints

import msgpack
import numpy as np

from robonav.pipeline.wire.codes import ErrorCode

SCHEMA_VERSION = 1
MAX_DEPTH = 16
"""Deepest nesting of maps and lists a payload may have (the deepest message needs 6)."""
MAX_COLLECTION_LENGTH = 1_000_000
"""Most entries of one msgpack map or list (arrays travel as bin, not as lists)."""
MAX_ARRAY_ELEMENTS = 1 << 31
"""Most elements of one array map, whatever its data length says."""

M = TypeVar("M", bound="Message")


class ProtocolError(ValueError):
    """A message could not be decoded or a request is not acceptable."""

    def __init__(self, code: ErrorCode, message: str, details: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.code = code
        self.message = message
        self.details = details or {}


@dataclass(frozen=True)
class ArraySpec:
    """Expected dtype family and shape of an array field; `None` in `shape` is any length."""

    dtype: str
    shape: tuple[int | str | None, ...]
    finite: bool = True


def array_field(dtype: str, shape: tuple[int | str | None, ...], *, finite: bool = True, optional: bool = False) -> Any:
    """Declare a dataclass field that travels as an array map."""
    spec = ArraySpec(dtype, shape, finite)
    if optional:
        return field(default=None, metadata={"array": spec})
    return field(metadata={"array": spec})


class Message:
    """Base of wire messages: frozen dataclasses with `to_wire`/`from_wire`."""

    ADDED_KEYS: ClassVar[tuple[str, ...]] = ()
    """Optional keys added within version 1 after 1.0: sent, they are listed in `ignorable`, so
    an older receiver drops them instead of refusing the message (docs/protocol.md, "Versions")."""

    def to_dict(self) -> dict[str, Any]:
        out = {"v": SCHEMA_VERSION, **self._fields_to_dict()}
        added = [key for key in self.ADDED_KEYS if key in out]
        if added:
            out[IGNORABLE_KEY] = added
        return out

    def _fields_to_dict(self) -> dict[str, Any]:
        """The fields as a plain map without `v`; a Message nested in another travels in this form."""
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):  # type: ignore[arg-type]
            value = getattr(self, f.name)
            if value is None:
                continue
            if "array" in f.metadata:
                out[f.name] = encode_array(np.asarray(value), f.metadata["array"].dtype)
            elif isinstance(value, enum.Enum):
                out[f.name] = value.value
            elif isinstance(value, Message):
                out[f.name] = value._fields_to_dict()
            elif dataclasses.is_dataclass(value) and not isinstance(value, type):
                out[f.name] = dataclasses.asdict(value)
            elif isinstance(value, tuple):
                out[f.name] = [v._fields_to_dict() if isinstance(v, Message) else v for v in value]
            else:
                out[f.name] = value
        return out

    def to_wire(self) -> bytes:
        return msgpack.packb(self.to_dict(), use_bin_type=True)

    @classmethod
    def from_dict(cls: type[M], obj: Any) -> M:
        if not isinstance(obj, dict):
            raise ProtocolError(ErrorCode.MALFORMED_MESSAGE, f"{cls.__name__}: expected a map, got {type(obj).__name__}")
        obj = dict(obj)
        version = obj.pop("v", None)
        if version is None:
            raise ProtocolError(ErrorCode.MALFORMED_MESSAGE, f"{cls.__name__}: missing schema version 'v'", {"key": "v"})
        # True == 1 and 1.0 == 1 in Python: the type is checked first, or they would pass as version 1.
        if isinstance(version, bool) or not isinstance(version, int):
            raise ProtocolError(ErrorCode.MALFORMED_MESSAGE,
                                f"{cls.__name__}: schema version 'v' must be an integer, got {type(version).__name__}",
                                {"key": "v"})
        if version != SCHEMA_VERSION:
            raise ProtocolError(ErrorCode.UNSUPPORTED_VERSION,
                                f"{cls.__name__}: schema version {version!r} is not supported (this side speaks {SCHEMA_VERSION})",
                                {"supported": [SCHEMA_VERSION], "got": version})
        return cls._fields_from_dict(obj)

    @classmethod
    def _fields_from_dict(cls: type[M], obj: dict[str, Any], prefix: str = "") -> M:
        """Decode the fields of a map without `v`; `prefix` is the key path of a nested message."""
        plan, known = _field_plan(cls)
        obj = _drop_ignorable(obj, known, cls.__name__, prefix)
        if not known.issuperset(obj):
            unknown = sorted(str(k) for k in obj if k not in known)
            raise ProtocolError(ErrorCode.MALFORMED_MESSAGE,
                                f"{cls.__name__}: unknown key '{prefix}{unknown[0]}' (known: {', '.join(sorted(known))})",
                                {"key": prefix + unknown[0]})
        kwargs: dict[str, Any] = {}
        owner = cls.__name__
        for name, has_default, decode in plan:
            value = obj.get(name)
            if value is None:
                if not has_default:
                    raise ProtocolError(ErrorCode.MALFORMED_MESSAGE, f"{owner}: missing key '{prefix}{name}'",
                                        {"key": prefix + name})
                continue
            kwargs[name] = decode(value, prefix + name, owner)
        try:
            return cls(**kwargs)
        except ProtocolError as exc:
            if prefix and "key" in exc.details:  # a nested message names its own keys: make them full paths
                exc.details["key"] = prefix + str(exc.details["key"])
            raise
        except (ValueError, TypeError, ArithmeticError, IndexError, KeyError) as exc:
            # Checks in a message's __post_init__ meet values of every size and sign: whatever
            # they raise on a decodable but unusable value is the sender's error, not ours.
            details = {"key": prefix.rstrip(".")} if prefix else {}
            where = f" (at '{prefix.rstrip('.')}')" if prefix else ""
            raise ProtocolError(ErrorCode.INVALID_REQUEST, f"{cls.__name__}{where}: {exc}", details) from exc

    @classmethod
    def from_wire(cls: type[M], payload: bytes) -> M:
        return cls.from_dict(unpack(payload))


IGNORABLE_KEY = "ignorable"


_Decoder = typing.Callable[[Any, str, str], Any]
"""Decodes one field's value: (value, key path, owning message's name) → the checked value."""


@functools.cache
def _field_plan(cls: type) -> tuple[tuple[tuple[str, bool, _Decoder], ...], frozenset[str]]:
    """A message class's fields in order as (name, has a default, decoder), and their names;
    built once per class. Resolving type hints and dispatching on them per value took most of
    the time of decoding a small message (a setpoint: 0.17 ms, at 1 kHz per subscriber)."""
    hints = get_type_hints(cls)
    plan = []
    for f in dataclasses.fields(cls):
        has_default = f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING
        if "array" in f.metadata:
            spec = f.metadata["array"]
            decode: _Decoder = lambda value, key, owner, spec=spec: decode_array(value, spec, key=key)  # noqa: E731
        else:
            decode = _decoder(hints[f.name])
        plan.append((f.name, has_default, decode))
    return tuple(plan), frozenset(name for name, _, _ in plan)


def _drop_ignorable(obj: dict[str, Any], known: frozenset[str], owner: str, prefix: str) -> dict[str, Any]:
    """The compatibility rule (docs/protocol.md, "Versions"): a map may list in `ignorable` keys
    a receiver that does not know them may ignore, so a newer peer's added optional keys do not
    break an older one. A listed key this side knows is decoded and checked as ever; an unknown
    key that is not listed is still MALFORMED_MESSAGE (a typo is never silently ignored)."""
    if IGNORABLE_KEY not in obj:
        return obj
    listed = obj[IGNORABLE_KEY]
    if not isinstance(listed, list) or not all(isinstance(k, str) for k in listed):
        raise ProtocolError(ErrorCode.MALFORMED_MESSAGE, f"{owner}: '{prefix}{IGNORABLE_KEY}' must be a list of strings",
                            {"key": prefix + IGNORABLE_KEY})
    return {k: v for k, v in obj.items() if k != IGNORABLE_KEY and (k in known or k not in listed)}


def unpack(payload: bytes) -> Any:
    """msgpack bytes → Python objects; garbage, and nesting or collections beyond the bounds
    (`MAX_DEPTH`, `MAX_COLLECTION_LENGTH`), raise MALFORMED_MESSAGE."""
    try:
        # msgpack checks the lengths before it allocates (and its own stack stops ~1000 levels deep).
        obj = msgpack.unpackb(payload, raw=False, strict_map_key=True, max_array_len=MAX_COLLECTION_LENGTH,
                              max_map_len=MAX_COLLECTION_LENGTH)
    except Exception as exc:  # msgpack raises several unrelated types for garbage
        raise ProtocolError(ErrorCode.MALFORMED_MESSAGE, f"payload is not valid msgpack: {exc}") from exc
    _check_depth(obj)
    return obj


def _check_depth(obj: Any) -> None:
    """MALFORMED_MESSAGE when maps and lists nest deeper than MAX_DEPTH (level by level: no
    recursion to exhaust). msgpack builds plain dicts and lists, so exact types are tested."""
    level = [obj] if type(obj) is dict or type(obj) is list else []
    depth = 1
    while level:
        if depth > MAX_DEPTH:
            raise ProtocolError(ErrorCode.MALFORMED_MESSAGE, f"payload nests maps and lists deeper than {MAX_DEPTH} levels")
        nested = []
        for value in level:
            for child in (value.values() if type(value) is dict else value):
                if type(child) is dict or type(child) is list:
                    nested.append(child)
        level = nested
        depth += 1


def encode_array(array: np.ndarray, dtype: str) -> dict[str, Any]:
    a = np.ascontiguousarray(array, dtype=np.dtype(dtype))
    return {"dtype": dtype, "shape": list(a.shape), "data": a.tobytes()}


_FLOAT_DTYPES = {"<f4", "<f8"}
_INT_DTYPES = {"<i4", "<i8", "<u1", "<i1", "<u4"}
_NUMPY_DTYPES = {name: np.dtype(name) for name in _FLOAT_DTYPES | _INT_DTYPES}


def decode_array(obj: Any, spec: ArraySpec, *, key: str) -> np.ndarray:
    """Decode and validate an array map against `spec`; converts float32/64 to `spec.dtype`."""
    if not isinstance(obj, dict) or len(obj) != 3 or "dtype" not in obj or "shape" not in obj or "data" not in obj:
        raise ProtocolError(ErrorCode.MALFORMED_MESSAGE, f"'{key}' must be an array map {{dtype, shape, data}}", {"key": key})
    dtype, shape, data = obj["dtype"], obj["shape"], obj["data"]
    family = _FLOAT_DTYPES if spec.dtype in _FLOAT_DTYPES else _INT_DTYPES
    if not isinstance(dtype, str) or dtype not in family:
        raise ProtocolError(ErrorCode.MALFORMED_MESSAGE, f"'{key}': dtype {dtype!r} not accepted (use one of {sorted(family)})",
                            {"key": key, "dtype": dtype})
    if not isinstance(shape, list) or len(shape) > MAX_DEPTH or \
            not all(isinstance(s, int) and not isinstance(s, bool) and 0 <= s <= MAX_ARRAY_ELEMENTS for s in shape):
        raise ProtocolError(ErrorCode.MALFORMED_MESSAGE,
                            f"'{key}': shape must be a list of ints in [0, {MAX_ARRAY_ELEMENTS}]", {"key": key})
    if not isinstance(data, bytes):
        raise ProtocolError(ErrorCode.MALFORMED_MESSAGE, f"'{key}': data must be bytes", {"key": key})
    if len(shape) != len(spec.shape) or any(e is not None and not isinstance(e, str) and e != s for e, s in zip(spec.shape, shape)):
        want = ["N" if e is None else e for e in spec.shape]
        raise ProtocolError(ErrorCode.INVALID_REQUEST, f"'{key}': shape {shape} does not match expected {want}",
                            {"key": key, "shape": shape, "expected": want})
    np_dtype = _NUMPY_DTYPES[dtype]
    # Python ints: a product of huge dimensions must not wrap around (int64) into a small size.
    elements = math.prod(shape)
    if elements > MAX_ARRAY_ELEMENTS:
        raise ProtocolError(ErrorCode.MALFORMED_MESSAGE, f"'{key}': shape {shape} has more than {MAX_ARRAY_ELEMENTS} elements",
                            {"key": key})
    expected_bytes = elements * np_dtype.itemsize
    if len(data) != expected_bytes:
        raise ProtocolError(ErrorCode.MALFORMED_MESSAGE, f"'{key}': {len(data)} data bytes, shape {shape} of {dtype} needs {expected_bytes}",
                            {"key": key})
    array = np.frombuffer(data, dtype=np_dtype).reshape(shape).astype(_NUMPY_DTYPES[spec.dtype], copy=True)
    if spec.finite and array.dtype.kind == "f" and not np.isfinite(array).all():
        bad = np.argwhere(~np.isfinite(array))[0].tolist()
        raise ProtocolError(ErrorCode.INVALID_REQUEST, f"'{key}' contains a non-finite value at index {bad}", {"key": key, "index": bad})
    return array


def _type_error(owner: str, key: str, what: str, value: Any) -> ProtocolError:
    return ProtocolError(ErrorCode.MALFORMED_MESSAGE, f"{owner}: '{key}' must be {what}, got {type(value).__name__}", {"key": key})


def _decode_float(value: Any, key: str, owner: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _type_error(owner, key, "a number", value)
    if not math.isfinite(value):
        raise ProtocolError(ErrorCode.INVALID_REQUEST, f"{owner}: '{key}' must be finite, got {value}", {"key": key})
    return float(value)


def _decode_bool(value: Any, key: str, owner: str) -> bool:
    if not isinstance(value, bool):
        raise _type_error(owner, key, "a bool", value)
    return value


def _decode_int(value: Any, key: str, owner: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise _type_error(owner, key, "an integer", value)
    return value


def _decode_str(value: Any, key: str, owner: str) -> str:
    if not isinstance(value, str):
        raise _type_error(owner, key, "a string", value)
    return value


def _decode_bytes(value: Any, key: str, owner: str) -> bytes:
    if not isinstance(value, bytes):
        raise _type_error(owner, key, "bytes (msgpack bin)", value)
    return value


_SCALAR_DECODERS: dict[Any, _Decoder] = {float: _decode_float, bool: _decode_bool, int: _decode_int, str: _decode_str,
                                         bytes: _decode_bytes}


@functools.cache
def _decoder(tp: Any) -> _Decoder:
    """The decoder of values of field type `tp`, built once per type."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        return _decoder(next(a for a in args if a is not type(None)))
    if tp in _SCALAR_DECODERS:
        return _SCALAR_DECODERS[tp]
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        return functools.partial(_decode_enum, tp)
    if isinstance(tp, type) and issubclass(tp, Message):
        return functools.partial(_decode_message, tp)
    if dataclasses.is_dataclass(tp):
        return functools.partial(_decode_dataclass, tp)
    if origin is tuple:
        return functools.partial(_decode_tuple, _decoder(args[0]), args[0] is str)
    if origin is dict or tp is dict:
        key_type, value_type = args if len(args) == 2 else (Any, Any)
        values = _decoder(value_type) if value_type in _SCALAR_DECODERS and value_type is not bytes else None
        return functools.partial(_decode_dict, key_type is str, values)
    raise TypeError(f"unsupported message field type {tp!r}")


def _decode_enum(tp: type[enum.Enum], value: Any, key: str, owner: str) -> enum.Enum:
    if not isinstance(value, str):
        raise _type_error(owner, key, "a string", value)
    try:
        return tp(value)
    except ValueError:
        known = [m.value for m in tp]
        raise ProtocolError(ErrorCode.INVALID_REQUEST, f"{owner}: '{key}' must be one of {known}, got {value!r}",
                            {"key": key, "known": known}) from None


def _decode_message(tp: type[Message], value: Any, key: str, owner: str) -> Message:
    if not isinstance(value, dict):
        raise ProtocolError(ErrorCode.MALFORMED_MESSAGE, f"{owner}: '{key}' must be a map", {"key": key})
    return tp._fields_from_dict(value, prefix=f"{key}.")


def _decode_dataclass(tp: type, value: Any, key: str, owner: str) -> Any:
    if not isinstance(value, dict):
        raise ProtocolError(ErrorCode.MALFORMED_MESSAGE, f"{owner}: '{key}' must be a map", {"key": key})
    plan, names = _field_plan(tp)
    value = _drop_ignorable(value, names, owner, f"{key}.")
    if set(value) - names or names - set(value):
        raise ProtocolError(ErrorCode.MALFORMED_MESSAGE, f"{owner}: '{key}' must have exactly the keys {sorted(names)}", {"key": key})
    fields = {name: decode(value[name], f"{key}.{name}", owner) for name, _, decode in plan}
    try:
        return tp(**fields)
    except (ValueError, TypeError, ArithmeticError) as exc:
        raise ProtocolError(ErrorCode.INVALID_REQUEST, f"{owner}: '{key}': {exc}", {"key": key}) from exc


def _decode_tuple(item: _Decoder, of_str: bool, value: Any, key: str, owner: str) -> tuple[Any, ...]:
    if not isinstance(value, list):
        raise ProtocolError(ErrorCode.MALFORMED_MESSAGE, f"{owner}: '{key}' must be a list", {"key": key})
    if of_str and all(isinstance(v, str) for v in value):  # joint names, on every setpoint and joint state
        return tuple(value)
    return tuple(item(v, f"{key}[{i}]", owner) for i, v in enumerate(value))


def _decode_dict(str_keys: bool, values: _Decoder | None, value: Any, key: str, owner: str) -> dict[Any, Any]:
    if not isinstance(value, dict):
        raise ProtocolError(ErrorCode.MALFORMED_MESSAGE, f"{owner}: '{key}' must be a map", {"key": key})
    # Keys travel as strings (msgpack maps here have string keys); a message that wants
    # other keys (label numbers) converts them itself.
    if str_keys and not all(isinstance(k, str) for k in value):
        raise ProtocolError(ErrorCode.MALFORMED_MESSAGE, f"{owner}: '{key}' must have string keys", {"key": key})
    if values is not None:
        return {k: values(v, f"{key}.{k}", owner) for k, v in value.items()}
    return dict(value)
