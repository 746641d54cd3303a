"""The writer's Foxglove conversion on bad and out-of-order input: the raw message is always
written, a copy that cannot be made is counted with its reason, and a path that came before the
robot description is drawn once the description arrives."""

from __future__ import annotations

import dataclasses
import io
import json
import math

import numpy as np
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap.reader import make_reader

from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.transforms import PoseSpec
from robonav.pipeline.wire.messages import ExecutorPath, JointState, RobotDescription
from robonav.services.planner.description import robot_description
from robonav.services.recording.files import RecordingWriter
from robonav.services.recording.foxglove import cube_field_bytes

ROOT = "robonav/fx"


def _write(messages: list[tuple[str, bytes]]) -> tuple[RecordingWriter, dict[str, list[bytes]], list[str]]:
    buffer = io.BytesIO()
    writer = RecordingWriter(buffer)
    for i, (key, payload) in enumerate(messages):
        writer.write(key, payload, receive_time_ns=1_000 + i, source_time_ns=1_000 + i)
    writer.finish()
    buffer.seek(0)
    reader = make_reader(buffer)
    out: dict[str, list[bytes]] = {}
    for _schema, channel, message in reader.iter_messages():
        out.setdefault(channel.topic, []).append(message.data)
    return writer, out, [a.name for a in reader.iter_attachments()]


def test_bad_payloads_are_recorded_raw_and_counted(panda: RobotModel) -> None:
    nan_state = JointState(stamp=1.0, names=("panda_joint1",), position=np.array([np.nan]), velocity=np.zeros(1))
    messages = [(f"{ROOT}/perception/occupancy", b"\x93not a map"),
                (f"{ROOT}/robot/joint_states", nan_state.to_wire()),
                (f"{ROOT}/robot/description", RobotDescription.from_wire(robot_description(panda).to_wire()).to_wire()
                 .replace(b"<robot", b"<rob0t", 1))]
    writer, topics, attachments = _write(messages)
    assert {t: len(v) for t, v in topics.items()} == {k: 1 for k, _ in messages}
    assert [topics[k][0] for k, _ in messages] == [p for _, p in messages]
    for key, _ in messages:
        assert writer.stats[key].foxglove_skipped == 1 and writer.stats[key].foxglove_error, key
    assert "finite" in (writer.stats[f"{ROOT}/robot/joint_states"].foxglove_error or "")
    assert attachments == []


def test_a_path_without_any_description_is_counted_as_not_drawn(panda: RobotModel) -> None:
    path = ExecutorPath(stamp=2.0, trajectory_id="t", joint_names=panda.joint_names,
                        path=np.array([panda.home_position_rad, panda.home_position_rad + 0.1]))
    buffer = io.BytesIO()
    writer = RecordingWriter(buffer)
    writer.write(f"{ROOT}/executor/path", path.to_wire(), receive_time_ns=1, source_time_ns=1)
    writer.settle_conversions()
    writer.finish()
    stats = writer.stats[f"{ROOT}/executor/path"]
    assert (stats.written, stats.foxglove_written, stats.foxglove_skipped) == (1, 0, 1)
    assert "without a robot description" in (stats.foxglove_error or "")


def test_a_path_before_the_description_is_drawn_when_it_comes(panda: RobotModel) -> None:
    path = ExecutorPath(stamp=2.0, trajectory_id="t", joint_names=panda.joint_names,
                        path=np.array([panda.home_position_rad, panda.home_position_rad + 0.1]))
    state = JointState(stamp=2.0, names=panda.joint_names, position=panda.home_position_rad, velocity=np.zeros(7))
    writer, topics, attachments = _write([(f"{ROOT}/executor/path", path.to_wire()),
                                          (f"{ROOT}/robot/joint_states", state.to_wire()),
                                          (f"{ROOT}/robot/description", robot_description(panda).to_wire()),
                                          (f"{ROOT}/robot/joint_states", state.to_wire())])
    assert writer.stats[f"{ROOT}/executor/path"].foxglove_skipped == 0
    (update,) = [SceneUpdate.FromString(d) for d in topics[f"{ROOT}/executor/path/foxglove"]]
    assert len(update.entities[0].lines[0].points) == 2
    # Joint states: a JSON copy always, link transforms once the robot is known.
    assert len(topics[f"{ROOT}/robot/joint_states/json"]) == 2
    assert len(topics[f"{ROOT}/robot/joint_states/foxglove"]) == 1
    assert json.loads(topics[f"{ROOT}/robot/joint_states/json"][0])["names"] == list(panda.joint_names)
    assert attachments == ["panda.urdf"]


def test_voxel_cubes_decode_with_the_official_schema() -> None:
    """The cubes written by copying one serialized cube decode, field by field, to what a cube
    built through the protobuf library holds (zeros included)."""
    centers = np.array([[0.0, 0.0, 0.0], [-1.25, 2.5, 1e-9], [3.0, -0.0, 7.75]])
    rgba = np.array([[0.0, 0.5, 1.0, 0.8], [1.0, 1.0, 1.0, 1.0], [0.25, 0.0, 0.0, 0.0]])
    entity = SceneEntity.FromString(SceneEntity(id="v").SerializeToString() + cube_field_bytes(centers, 0.02, rgba))
    assert entity.id == "v" and len(entity.cubes) == 3
    for cube, center, color in zip(entity.cubes, centers, rgba, strict=True):
        expected = SceneEntity().cubes.add()
        expected.pose.position.x, expected.pose.position.y, expected.pose.position.z = center
        expected.pose.orientation.w = 1.0
        expected.size.x = expected.size.y = expected.size.z = 0.02
        expected.color.r, expected.color.g, expected.color.b, expected.color.a = color
        assert cube == expected
    assert cube_field_bytes(np.zeros((0, 3)), 0.02, np.zeros((0, 4))) == b""


def test_no_foxglove_writes_the_raw_channels_only(panda: RobotModel) -> None:
    state = JointState(stamp=2.0, names=panda.joint_names, position=panda.home_position_rad, velocity=np.zeros(7))
    buffer = io.BytesIO()
    writer = RecordingWriter(buffer, foxglove_clouds=False)
    for i, (key, payload) in enumerate([(f"{ROOT}/robot/description", robot_description(panda).to_wire()),
                                        (f"{ROOT}/robot/joint_states", state.to_wire())]):
        writer.write(key, payload, receive_time_ns=i, source_time_ns=i)
    writer.finish()
    buffer.seek(0)
    reader = make_reader(buffer)
    summary = reader.get_summary()
    assert summary is not None
    assert {c.topic for c in summary.channels.values()} == {f"{ROOT}/robot/description", f"{ROOT}/robot/joint_states"}
    assert list(reader.iter_attachments()) == []


def test_the_robot_stands_in_the_recording_where_its_description_puts_it(panda: RobotModel) -> None:
    pose = PoseSpec((0.5, -1.0, 0.25), (0.0, 0.0, math.sin(0.3), math.cos(0.3)))
    posed = RobotModel.from_config(dataclasses.replace(panda.config, world_from_base=pose))
    description = RobotDescription.from_wire(robot_description(posed).to_wire())
    np.testing.assert_allclose(description.world_from_base, pose.matrix, atol=1e-15)
    q = posed.home_position_rad
    state = JointState(stamp=2.0, names=posed.joint_names, position=q, velocity=np.zeros(7))
    _, topics, _ = _write([(f"{ROOT}/robot/description", description.to_wire()),
                           (f"{ROOT}/robot/joint_states", state.to_wire())])
    (transforms,) = [FrameTransforms.FromString(d) for d in topics[f"{ROOT}/robot/joint_states/foxglove"]]
    root = transforms.transforms[0]  # world -> the URDF root, as robot_state_publisher sends it
    assert (root.parent_frame_id, root.child_frame_id) == ("world", "panda_link0")
    translation, rotation = root.translation, root.rotation
    np.testing.assert_allclose([translation.x, translation.y, translation.z], pose.position_m, atol=1e-12)
    np.testing.assert_allclose([rotation.x, rotation.y, rotation.z, rotation.w], pose.quat_xyzw, atol=1e-12)
