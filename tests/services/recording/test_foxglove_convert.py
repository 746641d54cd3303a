"""The writer's Foxglove conversion on bad and out-of-order input: the raw message is always
written, a copy that cannot be made is counted with its reason, and a path that came before the
robot description is drawn once the description arrives."""

from __future__ import annotations

import io
import json

import numpy as np
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap.reader import make_reader

from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.wire.messages import ExecutorPath, JointState, RobotDescription
from robonav.services.planner.description import robot_description
from robonav.services.recording.files import RecordingWriter

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


def test_a_path_before_the_description_is_drawn_when_it_comes(panda: RobotModel) -> None:
    path = ExecutorPath(stamp=2.0, trajectory_id="t", joint_names=panda.joint_names,
                        path=np.array([panda.home_position_rad, panda.home_position_rad + 0.1]))
    state = JointState(stamp=2.0, names=panda.joint_names, position=panda.home_position_rad, velocity=np.zeros(7))
    writer, topics, attachments = _write([(f"{ROOT}/executor/path", path.to_wire()),
                                          (f"{ROOT}/robot/joint_states", state.to_wire()),
                                          (f"{ROOT}/robot/description", robot_description(panda).to_wire()),
                                          (f"{ROOT}/robot/joint_states", state.to_wire())])
    assert writer.stats[f"{ROOT}/executor/path"].foxglove_skipped == 1
    (update,) = [SceneUpdate.FromString(d) for d in topics[f"{ROOT}/executor/path/foxglove"]]
    assert len(update.entities[0].lines[0].points) == 2
    # Joint states: a JSON copy always, link transforms once the robot is known.
    assert len(topics[f"{ROOT}/robot/joint_states/json"]) == 2
    assert len(topics[f"{ROOT}/robot/joint_states/foxglove"]) == 1
    assert json.loads(topics[f"{ROOT}/robot/joint_states/json"][0])["names"] == list(panda.joint_names)
    assert attachments == ["panda.urdf"]
