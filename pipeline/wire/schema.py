"""JSON Schema (2020-12) of every wire message, derived from the message dataclasses.

A message is a msgpack map; its JSON form, which the schemas describe, is the same map with
two mappings (docs/protocol.md, "JSON form"):

- msgpack bin (`bytes`: an array map's `data`, `Occupancy.octomap_binary`) is a string holding
  the bytes in standard base64 (RFC 4648, with padding): `contentEncoding: base64`;
- msgpack maps have string keys in both; integers, floats, strings, booleans, nil (`null`),
  lists and maps map one to one (a JSON number with a fraction or exponent is a float).

Array maps keep their `{dtype, shape, data}` form (not nested lists), so the JSON form holds
the exact bytes. Nothing here is written by hand per message: a new field or message appears in
the schemas when it appears in `messages.py`, and a test compares the committed schemas with
these.
"""

from __future__ import annotations

import base64
import dataclasses
import enum
import types
import typing
from typing import Any, get_type_hints

from robonav.pipeline.wire import messages
from robonav.pipeline.wire.codec import IGNORABLE_KEY, MAX_ARRAY_ELEMENTS, SCHEMA_VERSION, ArraySpec, Message

JSON_SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"
SCHEMA_ID_PREFIX = f"https://robonav.dev/schema/v{SCHEMA_VERSION}/"
"""`$id` of a message's schema: this prefix and `<Name>.schema.json` (an identifier, not a download)."""
_FLOAT_DTYPES = ["<f4", "<f8"]
_INT_DTYPES = ["<i1", "<i4", "<i8", "<u1", "<u4"]
_BYTES = {"type": "string", "contentEncoding": "base64"}


def message_classes() -> tuple[type[Message], ...]:
    """Every message class of `messages.py`, in the order they are defined."""
    return tuple(obj for obj in vars(messages).values()
                 if isinstance(obj, type) and issubclass(obj, Message) and obj is not Message
                 and obj.__module__ == messages.__name__)


def nested_classes() -> frozenset[type[Message]]:
    """Messages that travel only inside another message's map, without `v` (e.g. SceneObjectSpec)."""
    found: set[type[Message]] = set()
    for cls in message_classes():
        for tp in get_type_hints(cls).values():
            found.update(_messages_in(tp))
    return frozenset(found)


def _messages_in(tp: Any) -> set[type[Message]]:
    if isinstance(tp, type) and issubclass(tp, Message):
        return {tp}
    return {m for arg in typing.get_args(tp) for m in _messages_in(arg)}


def all_schemas() -> dict[str, dict[str, Any]]:
    """Message name -> its schema, for every message class."""
    return {cls.__name__: message_schema(cls) for cls in message_classes()}


def message_schema(cls: type[Message]) -> dict[str, Any]:
    """The JSON Schema of `cls`'s map: top-level messages carry `v`, nested ones do not. Nested
    messages and array maps are `$defs` of the same document, so each schema stands alone."""
    defs: dict[str, Any] = {}
    body = _object_schema(cls, defs, top_level=cls not in nested_classes())
    schema: dict[str, Any] = {"$schema": JSON_SCHEMA_DIALECT, "$id": f"{SCHEMA_ID_PREFIX}{cls.__name__}.schema.json",
                              "title": cls.__name__}
    if cls.__doc__ and not cls.__doc__.startswith(f"{cls.__name__}("):  # not dataclass's generated signature
        schema["description"] = " ".join(cls.__doc__.split())
    schema.update(body)
    if defs:
        schema["$defs"] = dict(sorted(defs.items()))
    return schema


def _object_schema(cls: type, defs: dict[str, Any], *, top_level: bool) -> dict[str, Any]:
    hints = get_type_hints(cls)
    properties: dict[str, Any] = {}
    required: list[str] = []
    if top_level:
        properties["v"] = {"const": SCHEMA_VERSION, "description": "schema version"}
        required.append("v")
    for f in dataclasses.fields(cls):
        has_default = f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING
        if "array" in f.metadata:
            value = _array_schema(f.metadata["array"], defs)
        else:
            value = _value_schema(_strip_optional(hints[f.name]), defs)
        if has_default:  # optional keys may also be sent as nil
            value = {"anyOf": [value, {"type": "null"}]}
        else:
            required.append(f.name)
        properties[f.name] = value
    if not issubclass(cls, Message):  # a plain dataclass value (CameraIntrinsics): every key required
        required = [f.name for f in dataclasses.fields(cls)]
    properties[IGNORABLE_KEY] = {"type": "array", "items": {"type": "string"},
                                 "description": "keys of this map a receiver that does not know them may ignore"}
    return {
        "type": "object", "properties": properties, "required": required,
        # Unknown keys are errors (a typo is not silently ignored) unless the sender lists them in
        # `ignorable`; which ones it lists, a schema cannot check, so any key passes then.
        "if": {"required": [IGNORABLE_KEY]}, "then": {"additionalProperties": True},
        "unevaluatedProperties": False,
    }


def _strip_optional(tp: Any) -> Any:
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        inner = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(inner) == 1:
            return inner[0]
    return tp


def _value_schema(tp: Any, defs: dict[str, Any]) -> dict[str, Any]:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp is bool:
        return {"type": "boolean"}
    if tp is int:
        return {"type": "integer"}
    if tp is float:
        return {"type": "number"}
    if tp is str:
        return {"type": "string"}
    if tp is bytes:
        return dict(_BYTES)
    if tp is Any:
        return {}
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        return {"type": "string", "enum": [m.value for m in tp]}
    if isinstance(tp, type) and issubclass(tp, Message):
        if tp.__name__ not in defs:
            defs[tp.__name__] = {}  # a placeholder first: a message may (one day) nest itself
            defs[tp.__name__] = _object_schema(tp, defs, top_level=False)
        return {"$ref": f"#/$defs/{tp.__name__}"}
    if dataclasses.is_dataclass(tp):
        if tp.__name__ not in defs:
            defs[tp.__name__] = _object_schema(tp, defs, top_level=False)
        return {"$ref": f"#/$defs/{tp.__name__}"}
    if origin is tuple:
        return {"type": "array", "items": _value_schema(args[0], defs)}
    if origin is dict or tp is dict:
        key_type, value_type = args if len(args) == 2 else (str, Any)
        schema: dict[str, Any] = {"type": "object", "additionalProperties": _value_schema(value_type, defs)}
        if key_type is int:  # integer keys travel as their decimal strings (label numbers)
            schema["propertyNames"] = {"pattern": "^-?[0-9]+$"}
        return schema
    raise TypeError(f"no JSON Schema for message field type {tp!r}")


def _array_schema(spec: ArraySpec, defs: dict[str, Any]) -> dict[str, Any]:
    """An array map `{dtype, shape, data}` of `spec`'s dtype family and rank; fixed dimensions are consts."""
    family = "float" if spec.dtype in _FLOAT_DTYPES else "int"
    name = f"array_{spec.dtype[1:]}_" + "_".join("n" if d is None or isinstance(d, str) else str(d) for d in spec.shape)
    if spec.finite is False and family == "float":
        name += "_nonfinite"
    if name not in defs:
        dims: list[dict[str, Any]] = [{"type": "integer", "minimum": 0, "maximum": MAX_ARRAY_ELEMENTS}
                                      if d is None or isinstance(d, str) else {"const": d} for d in spec.shape]
        defs[name] = {
            "type": "object",
            "description": f"array map: shape {['N' if d is None or isinstance(d, str) else d for d in spec.shape]}, "
                           f"sent as {spec.dtype}; data is the elements in C order, little-endian, "
                           f"prod(shape) x itemsize bytes" + ("" if spec.finite is False or family == "int"
                                                              else "; NaN and inf are refused"),
            "properties": {
                "dtype": {"enum": _FLOAT_DTYPES if family == "float" else _INT_DTYPES},
                "shape": {"type": "array", "prefixItems": dims, "items": False, "minItems": len(dims)},
                "data": dict(_BYTES),
            },
            "required": ["dtype", "shape", "data"],
            "additionalProperties": False,
        }
    return {"$ref": f"#/$defs/{name}"}


def to_json(value: Any) -> Any:
    """A decoded msgpack value (`codec.unpack`) in its JSON form: bytes become base64 strings."""
    if isinstance(value, bytes):
        return base64.b64encode(value).decode("ascii")
    if isinstance(value, dict):
        return {k: to_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_json(v) for v in value]
    return value


def from_json(value: Any, schema: dict[str, Any], root: dict[str, Any] | None = None) -> Any:
    """The inverse of `to_json`, guided by `schema`: base64 strings where it says bytes become bytes."""
    root = root if root is not None else schema
    if "$ref" in schema:
        schema = root["$defs"][schema["$ref"].rsplit("/", 1)[1]]
    if "anyOf" in schema:
        if value is None:
            return None
        schema = schema["anyOf"][0]
        return from_json(value, schema, root)
    if schema.get("contentEncoding") == "base64" and isinstance(value, str):
        return base64.b64decode(value, validate=True)
    if isinstance(value, dict):
        properties = schema.get("properties", {})
        extra = schema.get("additionalProperties")
        return {k: from_json(v, properties.get(k, extra if isinstance(extra, dict) else {}), root)
                for k, v in value.items()}
    if isinstance(value, list):
        items = schema.get("items")
        return [from_json(v, items if isinstance(items, dict) else {}, root) for v in value]
    return value
