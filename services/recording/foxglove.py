"""Foxglove-native channels derived from the raw ones while recording, so a recording opens as it is.

Beside each raw `msgpack` channel the writer adds what Foxglove (and Rerun's MCAP loader)
decode with their built-in schemas (the official `foxglove-schemas-protobuf` descriptors,
protobuf encoding) or with a JSON Schema (`json` encoding, `jsonschema` schema encoding):

| source key | derived topic | schema |
| --- | --- | --- |
| `camera/<id>/cloud` | `<key>/foxglove` | `foxglove.PointCloud` (frame: the camera id) |
| `cameras` | `<key>/foxglove` | `foxglove.FrameTransforms`: world -> each camera |
| `robot/joint_states` | `<key>/foxglove` | `foxglove.FrameTransforms`: world -> URDF root, parent -> child link of each joint |
| `robot/joint_states` | `<key>/json` | `robonav.JointStateJson` (names, position, velocity, by_name) |
| `perception/occupancy` | `<key>/foxglove` | `foxglove.SceneUpdate`: one cube per occupied voxel |
| `perception/clusters` | `<key>/foxglove` | `foxglove.SceneUpdate`: one box per cluster |
| `planner/scene_state` | `<key>/foxglove` | `foxglove.SceneUpdate`: objects, attached ones in their link's frame |
| `executor/path` | `<key>/foxglove` | `foxglove.SceneUpdate`: the end-effector's line through the path |
| `executor/status` | `<key>/json` | `robonav.ExecutorStatus` (the message's JSON form) |
| `robot/description` | `<key>/urdf` | `std_msgs/String` as JSON (`data`: the URDF text) |

and the URDF of `robot/description` as an attachment. The `std_msgs/String` channel is what
Foxglove's URDF layer reads a robot from (source "topic"); it then draws each link at the
frame of the same name that the joint states' transforms carry.

Link poses need the robot: joint states that arrive before `robot/description` get their JSON
copy but no transforms; a path that arrives before it is drawn when it comes (and counted as
skipped if it never does).
"""

from __future__ import annotations

import dataclasses
import json
import math
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from google.protobuf.timestamp_pb2 import Timestamp

from robonav.pipeline.markers import Primitive, box_centers_and_sizes, height_rgba, object_primitives
from robonav.pipeline.robot.link_frames import LinkFrames
from robonav.pipeline.transforms import quat_xyzw_from_rotation
from robonav.pipeline.types import FloatArray
from robonav.pipeline.wire.messages import (
    Cameras,
    Clusters,
    ExecutorPath,
    ExecutorStatus,
    JointState,
    Occupancy,
    PlanningSceneState,
    RobotDescription,
)
from robonav.pipeline.wire.schema import JSON_SCHEMA_DIALECT, message_schema
from robonav.services.recording.schema import FOXGLOVE_SUFFIX, message_class_for_key, protobuf_schema

JSON_SUFFIX = "/json"
"""A joint state or executor status on key K is also written on K + this suffix as JSON."""
WORLD_FRAME = "world"
VOXEL_ALPHA = 0.8
CLUSTER_RGBA = (1.0, 0.55, 0.0, 0.35)
SCENE_RGBA = (0.45, 0.55, 0.7, 0.8)
ATTACHED_RGBA = (0.3, 0.8, 0.3, 0.8)
PATH_RGBA = (1.0, 0.0, 0.78, 1.0)
"""The executed path's magenta of `robonav view`."""
PATH_THICKNESS_PX = 4.0

URDF_SUFFIX = "/urdf"
URDF_STRING_SCHEMA: dict[str, Any] = {
    "$schema": JSON_SCHEMA_DIALECT,
    "title": "std_msgs/String",
    "description": "The URDF text of robot/description, as a ROS std_msgs/String (what Foxglove's URDF layer reads).",
    "type": "object",
    "properties": {"data": {"type": "string"}},
    "required": ["data"],
    "additionalProperties": False,
}
JOINT_STATE_JSON_SCHEMA: dict[str, Any] = {
    "$schema": JSON_SCHEMA_DIALECT,
    "title": "robonav.JointStateJson",
    "description": "A robot/joint_states message for plotting: vectors as number lists in `names` "
                   "order, and the same values by joint name.",
    "type": "object",
    "properties": {
        "stamp": {"type": "number", "description": "Unix time of the state [s]"},
        "names": {"type": "array", "items": {"type": "string"}},
        "position": {"type": "array", "items": {"type": "number"}, "description": "[rad, or m for prismatic]"},
        "velocity": {"type": "array", "items": {"type": "number"}, "description": "[rad/s, or m/s]"},
        "by_name": {"type": "object", "additionalProperties": {
            "type": "object", "properties": {"position": {"type": "number"}, "velocity": {"type": "number"}},
            "required": ["position", "velocity"], "additionalProperties": False}},
    },
    "required": ["stamp", "names", "position", "velocity", "by_name"],
    "additionalProperties": False,
}


@dataclass(frozen=True)
class Derived:
    """One message of a derived channel."""

    topic: str
    message_encoding: str
    """`protobuf` or `json`."""
    schema_name: str
    schema_encoding: str
    """`protobuf` (a FileDescriptorSet) or `jsonschema`."""
    schema: bytes
    data: bytes


@dataclass(frozen=True)
class Attachment:
    name: str
    media_type: str
    data: bytes


def _protobuf(topic: str, message: Any) -> Derived:
    full_name = message.DESCRIPTOR.full_name
    if full_name not in _PROTOBUF_SCHEMAS:
        _PROTOBUF_SCHEMAS[full_name] = protobuf_schema(type(message))
    name, schema = _PROTOBUF_SCHEMAS[full_name]
    return Derived(topic, "protobuf", name, "protobuf", schema, message.SerializeToString())


def _json(topic: str, schema: dict[str, Any], value: dict[str, Any]) -> Derived:
    # allow_nan=False: a NaN would make the line invalid JSON; callers drop such messages first.
    return Derived(topic, "json", schema["title"], "jsonschema", json.dumps(schema, sort_keys=True).encode(),
                   json.dumps(value, allow_nan=False).encode())


_PROTOBUF_SCHEMAS: dict[str, tuple[str, bytes]] = {}
_EXECUTOR_STATUS_SCHEMA = {**message_schema(ExecutorStatus), "title": "robonav.ExecutorStatus"}


def timestamp(stamp_s: float) -> Timestamp:
    seconds = math.floor(stamp_s)
    return Timestamp(seconds=seconds, nanos=min(int(round((stamp_s - seconds) * 1e9)), 999_999_999))


def frame_transform(stamp_s: float, parent: str, child: str, parent_from_child: FloatArray) -> FrameTransform:
    out = FrameTransform(timestamp=timestamp(stamp_s), parent_frame_id=parent, child_frame_id=child)
    x, y, z = (float(v) for v in parent_from_child[:3, 3])
    out.translation.x, out.translation.y, out.translation.z = x, y, z
    qx, qy, qz, qw = (float(v) for v in quat_xyzw_from_rotation(parent_from_child[:3, :3]))
    out.rotation.x, out.rotation.y, out.rotation.z, out.rotation.w = qx, qy, qz, qw
    return out


def _color(rgba: tuple[float, ...] | FloatArray) -> Color:
    r, g, b, a = (float(v) for v in rgba)
    return Color(r=r, g=g, b=b, a=a)


def _set_pose(pose: Any, position: Any, quat_xyzw: Any = (0.0, 0.0, 0.0, 1.0)) -> None:
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in position)
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = (float(v) for v in quat_xyzw)


def _add_primitive(entity: SceneEntity, primitive: Primitive, rgba: tuple[float, ...]) -> None:
    if primitive.kind == "triangles":
        assert primitive.points_m is not None
        shape = entity.triangles.add(color=_color(rgba))
        _set_pose(shape.pose, primitive.position_m, primitive.quat_xyzw)
        for x, y, z in primitive.points_m.tolist():
            shape.points.add(x=x, y=y, z=z)
        return
    shape = {"cube": entity.cubes, "sphere": entity.spheres, "cylinder": entity.cylinders}[primitive.kind].add()
    _set_pose(shape.pose, primitive.position_m, primitive.quat_xyzw)
    shape.size.x, shape.size.y, shape.size.z = primitive.size_m
    shape.color.CopyFrom(_color(rgba))
    if primitive.kind == "cylinder":
        shape.bottom_scale = shape.top_scale = 1.0


def _cube_template() -> tuple[np.ndarray, dict[str, int]]:
    """One `cubes` element of a SceneEntity, serialized by protobuf with every double set to a
    marker value, and the byte offset of each double in it."""
    entity = SceneEntity()
    cube = entity.cubes.add()
    fields = {"x": 1.5, "y": 2.5, "z": 3.5, "w": 4.5, "sx": 5.5, "sy": 6.5, "sz": 7.5,
              "r": 8.5, "g": 9.5, "b": 10.5, "a": 11.5}
    cube.pose.position.x, cube.pose.position.y, cube.pose.position.z = fields["x"], fields["y"], fields["z"]
    cube.pose.orientation.w = fields["w"]
    cube.size.x, cube.size.y, cube.size.z = fields["sx"], fields["sy"], fields["sz"]
    cube.color.r, cube.color.g, cube.color.b, cube.color.a = fields["r"], fields["g"], fields["b"], fields["a"]
    record = entity.SerializeToString()
    offsets = {}
    for name, value in fields.items():
        marker = struct.pack("<d", value)
        assert record.count(marker) == 1, f"cube template: marker of {name} is not unique"
        offsets[name] = record.index(marker)
    return np.frombuffer(record, dtype=np.uint8), offsets


_CUBE_TEMPLATE, _CUBE_OFFSETS = _cube_template()


def cube_field_bytes(centers_m: FloatArray, side_m: float, rgba: FloatArray) -> bytes:
    """`cubes` elements of a SceneEntity, serialized: one axis-aligned cube of side `side_m` per
    row of `centers_m` (N, 3), colored by `rgba` (N, 4).

    Why not the protobuf library per cube: a map holds tens of thousands of voxels, and setting
    their 14 fields one by one costs ~5 us each (85 ms for a map of 17k). Every double of a cube
    is a fixed 8-byte field, so the serialization protobuf makes of one cube is the same bytes
    for every cube but the doubles: this copies it N times and writes the doubles with numpy.
    Tests decode the result with the official schema.
    """
    n = len(centers_m)
    out = np.tile(_CUBE_TEMPLATE, (n, 1))
    columns = {"x": centers_m[:, 0], "y": centers_m[:, 1], "z": centers_m[:, 2], "w": np.ones(n),
               "sx": np.full(n, side_m), "sy": np.full(n, side_m), "sz": np.full(n, side_m),
               "r": rgba[:, 0], "g": rgba[:, 1], "b": rgba[:, 2], "a": rgba[:, 3]}
    for name, values in columns.items():
        offset = _CUBE_OFFSETS[name]
        out[:, offset:offset + 8] = np.ascontiguousarray(values, dtype="<f8").view(np.uint8).reshape(n, 8)
    return out.tobytes()


def _scene_update(stamp_s: float) -> SceneUpdate:
    """A SceneUpdate that first deletes every entity this topic drew before: each message is the whole picture."""
    update = SceneUpdate()
    update.deletions.add(timestamp=timestamp(stamp_s), type=SceneEntityDeletion.ALL)
    return update


def _entity(update: SceneUpdate, stamp_s: float, entity_id: str, frame_id: str = WORLD_FRAME) -> SceneEntity:
    return update.entities.add(timestamp=timestamp(stamp_s), frame_id=frame_id, id=entity_id)


class FoxgloveConverter:
    """Turns raw payloads into derived channel messages; keeps the robot and the latest path.

    `convert` raises ValueError (a ProtocolError, or a value no viewer can draw) for a payload
    it cannot convert: the raw message is recorded all the same and the caller counts the skip.
    """

    def __init__(self) -> None:
        self._handlers: dict[type, Callable[[str, Any], list[Derived]]] = {
            Cameras: self._cameras, JointState: self._joint_state, Occupancy: self._occupancy, Clusters: self._clusters,
            PlanningSceneState: self._scene, ExecutorPath: self._path, ExecutorStatus: self._status}
        self._robot: RobotDescription | None = None
        self._links: LinkFrames | None = None
        self._pending_path: tuple[str, ExecutorPath] | None = None

    def convert(self, key: str, payload: bytes) -> tuple[list[Derived], list[Attachment]]:
        cls = message_class_for_key(key)
        if cls is RobotDescription:
            return self._robot_description(key, RobotDescription.from_wire(payload))
        if cls is None or cls not in self._handlers:
            return [], []
        return self._handlers[cls](key, cls.from_wire(payload)), []

    def undrawn(self) -> dict[str, str]:
        """Key -> why: messages held back for the robot description that never came."""
        if self._pending_path is None:
            return {}
        return {self._pending_path[0]: "executor path without a robot description in the recording: not drawn"}

    def _robot_description(self, key: str, robot: RobotDescription) -> tuple[list[Derived], list[Attachment]]:
        def what_counts(r: RobotDescription) -> tuple[Any, ...]:  # the stamp changes with every planner start
            pose = None if r.world_from_base is None else r.world_from_base.tobytes()
            return r.urdf, r.base_frame, r.end_effector_link, sorted(r.fixed_joint_positions.items()), pose

        if self._robot is not None and what_counts(robot) == what_counts(self._robot):
            return [], []
        try:
            self._links = LinkFrames(robot.urdf, robot.base_frame, robot.fixed_joint_positions, robot.world_from_base)
            self._robot = robot
        except ValueError:  # counted by the writer with its reason; link poses wait for a good one
            self._robot, self._links = None, None
            raise
        attachment = Attachment(f"{robot.name}.urdf", "application/xml", robot.urdf.encode())
        derived = [_json(key + URDF_SUFFIX, URDF_STRING_SCHEMA, {"data": robot.urdf})]
        if self._pending_path is not None:
            derived += self._path(*self._pending_path)
        return derived, [attachment]

    def _cameras(self, key: str, cameras: Cameras) -> list[Derived]:
        message = FrameTransforms(transforms=[
            frame_transform(cameras.stamp, WORLD_FRAME, c.camera_id, c.world_from_camera) for c in cameras.cameras])
        return [_protobuf(key + FOXGLOVE_SUFFIX, message)]

    def _joint_state(self, key: str, state: JointState) -> list[Derived]:
        names, position, velocity = list(state.names), state.position.tolist(), state.velocity.tolist()
        if not (np.isfinite(state.position).all() and np.isfinite(state.velocity).all()):
            raise ValueError("joint state with a non-finite position or velocity: not drawn or plotted")
        by_name = {n: {"position": p, "velocity": v} for n, p, v in zip(names, position, velocity, strict=True)}
        out = [_json(key + JSON_SUFFIX, JOINT_STATE_JSON_SCHEMA, {
            "stamp": state.stamp, "names": names, "position": position, "velocity": velocity, "by_name": by_name})]
        if self._links is not None:
            tree = self._links.tree_transforms(dict(zip(names, position, strict=True)), WORLD_FRAME)
            out.append(_protobuf(key + FOXGLOVE_SUFFIX, FrameTransforms(transforms=[
                frame_transform(state.stamp, parent, child, pose) for parent, child, pose in tree])))
        return out

    def _occupancy(self, key: str, occupancy: Occupancy) -> list[Derived]:
        update = _scene_update(occupancy.stamp)
        header = SceneEntity(timestamp=timestamp(occupancy.stamp), frame_id=occupancy.frame_id, id="occupied_voxels")
        centers = np.asarray(occupancy.occupied_centers_m, dtype=np.float64)
        cubes = cube_field_bytes(centers, float(occupancy.resolution_m), height_rgba(centers[:, 2], VOXEL_ALPHA))
        # Serialized messages concatenate into one whose repeated fields hold both parts' elements.
        update.entities.append(SceneEntity.FromString(header.SerializeToString() + cubes))
        return [_protobuf(key + FOXGLOVE_SUFFIX, update)]

    def _clusters(self, key: str, clusters: Clusters) -> list[Derived]:
        update = _scene_update(clusters.stamp)
        centers, sizes = box_centers_and_sizes(clusters.bbox_min_m, clusters.bbox_max_m)
        labels = list(clusters.labels) if len(clusters.labels) == len(centers) else [""] * len(centers)
        for cluster_id, center, size, label in zip(clusters.ids.tolist(), centers, sizes, labels, strict=True):
            entity = _entity(update, clusters.stamp, f"cluster {cluster_id}", clusters.frame_id)
            cube = entity.cubes.add(color=_color(CLUSTER_RGBA))
            _set_pose(cube.pose, center)
            cube.size.x, cube.size.y, cube.size.z = (float(v) for v in size)
            text = entity.texts.add(text=f"{label or 'cluster'} {cluster_id}", billboard=True, font_size=14.0,
                                    scale_invariant=True, color=_color((1.0, 1.0, 1.0, 1.0)))
            _set_pose(text.pose, (center[0], center[1], center[2] + size[2] / 2.0))
        return [_protobuf(key + FOXGLOVE_SUFFIX, update)]

    def _scene(self, key: str, scene: PlanningSceneState) -> list[Derived]:
        update = _scene_update(scene.stamp)
        for obj in scene.objects:
            entity = _entity(update, scene.stamp, obj.name)
            for primitive in object_primitives(obj, WORLD_FRAME):
                _add_primitive(entity, primitive, SCENE_RGBA)
        for attached in scene.attached:
            # Posed in its link's frame: it moves with the link's transform of the joint states.
            entity = _entity(update, scene.stamp, attached.object.name, attached.link)
            entity.frame_locked = True
            for primitive in object_primitives(attached.object):
                _add_primitive(entity, dataclasses.replace(primitive, frame_id=attached.link), ATTACHED_RGBA)
        return [_protobuf(key + FOXGLOVE_SUFFIX, update)]

    def _path(self, key: str, path: ExecutorPath) -> list[Derived]:
        if self._links is None or self._robot is None:  # drawn when the description comes (`undrawn` if never)
            self._pending_path = (key, path)
            return []
        self._pending_path = None
        points = self._links.link_positions(path.joint_names, path.path, self._robot.end_effector_link)
        update = _scene_update(path.stamp)
        entity = _entity(update, path.stamp, f"path {path.trajectory_id}")
        line = entity.lines.add(type=LinePrimitive.LINE_STRIP, thickness=PATH_THICKNESS_PX, scale_invariant=True,
                                color=_color(PATH_RGBA))
        line.pose.orientation.w = 1.0
        for x, y, z in points.tolist():
            line.points.add(x=x, y=y, z=z)
        return [_protobuf(key + FOXGLOVE_SUFFIX, update)]

    def _status(self, key: str, status: ExecutorStatus) -> list[Derived]:
        return [_json(key + JSON_SUFFIX, _EXECUTOR_STATUS_SCHEMA, status.to_dict())]
