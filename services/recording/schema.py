"""What a recording's channels declare: JSON Schemas of the msgpack maps, and Foxglove copies of clouds.

Each recorded key expression gets one MCAP channel with message encoding `msgpack` whose
schema (encoding `jsonschema`) is derived from the message dataclass in
`pipeline/messages.py` that travels on that key. Keys this package does not publish get a
generic "msgpack map" schema. Camera clouds are also written as `foxglove.PointCloud`
(protobuf schemas from `foxglove-schemas-protobuf`), which Foxglove and Rerun open directly;
`foxglove.py` derives the other Foxglove channels with the descriptors `protobuf_schema` gives.
"""

from __future__ import annotations

import dataclasses
import json
import types
import typing
from typing import Any, get_args, get_origin, get_type_hints

import numpy as np
import zenoh
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud as FoxglovePointCloud
from google.protobuf.descriptor_pb2 import FileDescriptorSet

from robonav.pipeline.wire.codec import IGNORABLE_KEY, Message
from robonav.pipeline.wire.messages import (
    Cameras,
    Clusters,
    ExecutorPath,
    ExecutorStatus,
    JointState,
    Occupancy,
    PlanningSceneState,
    PointCloud,
    RobotDescription,
    Setpoint,
)

MSGPACK_ENCODING = "msgpack"
JSONSCHEMA_ENCODING = "jsonschema"
FOXGLOVE_SUFFIX = "/foxglove"
"""A cloud on key K is also written on topic K + this suffix as `foxglove.PointCloud`."""

# Key patterns (under any cell) and the message each carries.
_KEY_MESSAGES: tuple[tuple[str, type[Message]], ...] = (
    ("robonav/*/camera/*/cloud", PointCloud),
    ("robonav/*/robot/joint_states", JointState),
    ("robonav/*/perception/occupancy", Occupancy),
    ("robonav/*/executor/setpoint", Setpoint),
    ("robonav/*/executor/status", ExecutorStatus),
    ("robonav/*/executor/path", ExecutorPath),
    ("robonav/*/perception/clusters", Clusters),
    ("robonav/*/planner/scene_state", PlanningSceneState),
    ("robonav/*/robot/description", RobotDescription),
    ("robonav/*/cameras", Cameras),
)
_ARRAY_SCHEMA: dict[str, Any] = {
    "type": "object",
    "description": "numeric array: little-endian elements in C order",
    "properties": {
        "dtype": {"type": "string", "enum": ["<f4", "<f8", "<i1", "<u1", "<i4", "<u4", "<i8"]},
        "shape": {"type": "array", "items": {"type": "integer", "minimum": 0}},
        "data": {"description": "msgpack bin: prod(shape) * itemsize bytes"},
    },
    "required": ["dtype", "shape", "data"],
    "additionalProperties": False,
}


def message_class_for_key(key: str) -> type[Message] | None:
    """The wire message that travels on `key`, or None for keys robonav does not publish."""
    expr = zenoh.KeyExpr(key)
    for pattern, cls in _KEY_MESSAGES:
        if zenoh.KeyExpr(pattern).includes(expr):
            return cls
    return None


def is_cloud_key(key: str) -> bool:
    return message_class_for_key(key) is PointCloud


def json_schema_for_key(key: str) -> tuple[str, bytes]:
    """(schema name, JSON Schema bytes) describing the msgpack map recorded on `key`."""
    cls = message_class_for_key(key)
    if cls is None:
        schema = {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": "msgpack",
                  "description": f"payloads of {key} as published (not a robonav message)"}
        return "msgpack", json.dumps(schema).encode()
    schema = {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": f"robonav.{cls.__name__}",
              **_object_schema(cls, with_version=True)}
    return f"robonav.{cls.__name__}", json.dumps(schema, sort_keys=True).encode()


def _object_schema(cls: type, *, with_version: bool) -> dict[str, Any]:
    hints = get_type_hints(cls)
    properties: dict[str, Any] = {"v": {"type": "integer", "const": 1}} if with_version else {}
    required = ["v"] if with_version else []
    for f in dataclasses.fields(cls):
        if "array" in f.metadata:
            properties[f.name] = _ARRAY_SCHEMA
        else:
            properties[f.name] = _value_schema(hints[f.name])
        if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            required.append(f.name)
    if with_version:  # a message lists the keys it added after 1.0 (docs/protocol.md, "Versions")
        properties[IGNORABLE_KEY] = {"type": "array", "items": {"type": "string"}}
    return {"type": "object", "properties": properties, "required": required, "additionalProperties": False}


def _value_schema(tp: Any) -> dict[str, Any]:
    origin, args = get_origin(tp), get_args(tp)
    if origin in (typing.Union, types.UnionType):
        options = [_value_schema(a) for a in args if a is not type(None)]
        return options[0] if len(options) == 1 else {"anyOf": options}
    if origin is tuple:
        return {"type": "array", "items": _value_schema(args[0]) if args else {}}
    if origin is dict or tp is dict:
        return {"type": "object"}
    if dataclasses.is_dataclass(tp):
        return _object_schema(tp, with_version=False)  # type: ignore[arg-type]
    simple = {float: "number", int: "integer", str: "string", bool: "boolean"}
    if tp in simple:
        return {"type": simple[tp]}
    if tp is bytes:
        return {"description": "msgpack bin"}
    if tp is np.ndarray:
        return _ARRAY_SCHEMA
    return {}


def foxglove_point_cloud_schema() -> tuple[str, bytes]:
    """(schema name, serialized FileDescriptorSet) of `foxglove.PointCloud` and its dependencies."""
    return protobuf_schema(FoxglovePointCloud)


def protobuf_schema(message_type: Any) -> tuple[str, bytes]:
    """(full name, serialized FileDescriptorSet) of a protobuf message type and the files it
    depends on: what MCAP's `protobuf` schema encoding holds."""
    descriptors = FileDescriptorSet()
    seen: set[str] = set()

    def add(file_descriptor: Any) -> None:
        for dependency in file_descriptor.dependencies:
            if dependency.name not in seen:
                seen.add(dependency.name)
                add(dependency)
        file_descriptor.CopyToProto(descriptors.file.add())

    add(message_type.DESCRIPTOR.file)
    return message_type.DESCRIPTOR.full_name, descriptors.SerializeToString()


def foxglove_point_cloud(payload: bytes) -> tuple[bytes, int]:
    """A robonav PointCloud payload as serialized `foxglove.PointCloud` and the cloud's `seq`.

    The points stay in the camera's optical frame: `frame_id` is the camera id.

    Raises:
        ProtocolError: the payload is not a valid PointCloud.
    """
    cloud = PointCloud.from_wire(payload)
    seconds = int(cloud.stamp // 1)
    message = FoxglovePointCloud(
        frame_id=cloud.camera_id,
        point_stride=12,
        fields=[PackedElementField(name=axis, offset=4 * i, type=PackedElementField.FLOAT32)
                for i, axis in enumerate("xyz")],
        data=np.ascontiguousarray(cloud.points, dtype="<f4").tobytes(),
    )
    message.timestamp.seconds = seconds
    message.timestamp.nanos = min(int(round((cloud.stamp - seconds) * 1e9)), 999_999_999)
    message.pose.orientation.w = 1.0
    return message.SerializeToString(), cloud.seq
