"""A recording of the live stack (real sim, perception, planner and executor processes) opens in
Foxglove as it is: every channel decodes with the schema it declares (protobuf descriptors built
from the file alone, JSON Schema validation of JSON and msgpack maps), and the derived channels
say what the raw ones say: links where the robot model puts them, one cube per occupied voxel,
the planner's objects, the executor's path as the end effector's line, the URDF attached."""

from __future__ import annotations

import json
import re
import time
from pathlib import Path
from typing import Any

import jsonschema
import msgpack
import numpy as np
import pytest
import zenoh
from google.protobuf import descriptor_pool, message_factory
from google.protobuf.descriptor_pb2 import FileDescriptorSet
from mcap.reader import make_reader

from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.transforms import make_transform
from robonav.pipeline.wire.messages import (
    Cameras,
    ErrorReply,
    ExecuteResponse,
    ExecutorPath,
    JointState,
    Occupancy,
    PlanResponse,
    RobotDescription,
    SceneObjectSpec,
    SceneRequest,
    SceneResponse,
)
from robonav.services.client import RobonavClient
from robonav.services.config import load_config
from robonav.services.recording.record import Recorder

from ..conftest import wait_for

DEFAULT = load_config()
ROBOT = RobotModel.from_config(DEFAULT.robot)
# Out of the arm's reach (0.85 m), so planning is unaffected; one object of every shape.
OBJECTS = (
    SceneObjectSpec("fx_box", "box", (0.0, -1.3, 0.2), size_m=(0.1, 0.2, 0.3)),
    SceneObjectSpec("fx_sphere", "sphere", (0.3, -1.3, 0.2), radius_m=0.05),
    SceneObjectSpec("fx_cylinder", "cylinder", (-0.3, -1.3, 0.2), radius_m=0.04, length_m=0.2),
    SceneObjectSpec("fx_capsule", "capsule", (0.6, -1.3, 0.2), radius_m=0.04, length_m=0.2),
    SceneObjectSpec("fx_mesh", "mesh", (-0.6, -1.3, 0.2), vertices_m=np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0.0]]),
                    triangles=np.array([[0, 1, 2]])),
)
# Just beyond the finger tips (0.1034 m along the hand's z), touching only the fingers.
TOOL = SceneObjectSpec("fx_tool", "sphere", (0.0, 0.0, 0.13), radius_m=0.01, frame_id="panda_hand")


def _move(client: RobonavClient, goal: np.ndarray) -> None:
    for attempt in range(3):
        plan = client.plan(goal, allowed_planning_time=5.0, seed=21 + attempt)
        assert isinstance(plan, PlanResponse), plan
        execution = client.execute(plan.path, joint_names=plan.joint_names, replan=True)
        if isinstance(execution, ErrorReply) and execution.code == "PATH_IN_COLLISION":
            continue  # a voxel came in after the plan: plan again
        assert isinstance(execution, ExecuteResponse), execution
        result = client.wait_for_trajectory(execution.trajectory_id, execution.duration_s + 20.0)
        assert result == "succeeded", (result, client.status)
        return
    raise AssertionError("no plan to the goal survived the execute check three times")


def _protobuf_class(name: str, schema: bytes) -> Any:
    """The message class a reader builds from the file's own FileDescriptorSet (no compiled schema)."""
    pool = descriptor_pool.DescriptorPool()
    for file in FileDescriptorSet.FromString(schema).file:
        pool.Add(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


@pytest.fixture(scope="module")
def recording(client: RobonavClient, session: zenoh.Session, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A few seconds of the stack: scene objects added and one attached, a planned move executed."""
    path = tmp_path_factory.mktemp("foxglove") / "stack.mcap"
    recorder = Recorder(session, path, [f"{client.keys.root}/**"])
    started = time.monotonic()
    try:
        assert isinstance(client.scene(SceneRequest(operation="add", objects=OBJECTS)), SceneResponse)
        attached = client.scene(SceneRequest(operation="attach", link="panda_hand", objects=(TOOL,),
                                             touch_links=("panda_leftfinger", "panda_rightfinger")))
        assert isinstance(attached, SceneResponse), attached
        start = client.joint_state.position.copy() if client.joint_state is not None else None
        assert start is not None
        goal = np.array(DEFAULT.demo.goals_rad[0])
        _move(client, goal if np.abs(goal - start).max() > 0.1 else np.array(DEFAULT.robot.home_position_rad))
        assert wait_for(lambda: recorder.stats.received[client.keys.clusters] > 0, 10.0), "no clusters published"
    finally:
        removed = client.scene(SceneRequest(operation="remove", names=tuple(o.name for o in (*OBJECTS, TOOL))))
        time.sleep(0.3)  # the scene without them is recorded too
        summary = recorder.close()
    print(f"recorded {time.monotonic() - started:.1f} s: {path.stat().st_size / 2**20:.2f} MB, "
          f"{summary['written']} raw messages")
    assert isinstance(removed, SceneResponse), removed
    assert summary["dropped"] == 0 and summary["write_error"] is None, summary
    skipped = {k: (v["foxglove_skipped"], v.get("foxglove_error")) for k, v in summary["keys"].items()
               if v["foxglove_skipped"]}
    assert not skipped, skipped
    return path


def _world_from(parent_of: dict[str, Any], frame: str) -> np.ndarray:
    """world_from_frame, walking FrameTransforms up to `world` as a viewer's transform tree does."""
    pose = np.eye(4)
    while frame != "world":
        t = parent_of[frame]
        parent_from_child = make_transform([t.translation.x, t.translation.y, t.translation.z],
                                           [t.rotation.x, t.rotation.y, t.rotation.z, t.rotation.w])
        pose, frame = parent_from_child @ pose, t.parent_frame_id
    return pose


def _read(path: Path) -> tuple[dict[str, list[tuple[int, bytes]]], dict[str, Any], list[Any]]:
    """Messages (log time, data) per topic, (channel, schema) per topic, attachments."""
    messages: dict[str, list[tuple[int, bytes]]] = {}
    channels: dict[str, Any] = {}
    with open(path, "rb") as f:
        reader = make_reader(f)
        for schema, channel, message in reader.iter_messages():
            channels[channel.topic] = (channel, schema)
            messages.setdefault(channel.topic, []).append((message.log_time, message.data))
        attachments = list(reader.iter_attachments())
    return messages, channels, attachments


def test_every_channel_decodes_with_its_declared_schema(recording: Path, client: RobonavClient) -> None:
    messages, channels, _ = _read(recording)
    root = client.keys.root
    derived = {f"{root}/cameras/foxglove": "foxglove.FrameTransforms",
               f"{root}/robot/joint_states/foxglove": "foxglove.FrameTransforms",
               f"{root}/robot/joint_states/json": "robonav.JointStateJson",
               f"{root}/perception/occupancy/foxglove": "foxglove.SceneUpdate",
               f"{root}/perception/clusters/foxglove": "foxglove.SceneUpdate",
               f"{root}/planner/scene_state/foxglove": "foxglove.SceneUpdate",
               f"{root}/executor/path/foxglove": "foxglove.SceneUpdate",
               f"{root}/executor/status/json": "robonav.ExecutorStatus",
               f"{root}/robot/description/urdf": "std_msgs/String"}
    # Every configured camera's cloud, as foxglove.PointCloud in its own frame.
    derived.update({f"{root}/camera/{c.camera_id}/cloud/foxglove": "foxglove.PointCloud" for c in DEFAULT.cameras
                    if c.output in ("cloud", "both")})
    assert {t: channels[t][1].name for t in derived if t in channels} == derived
    for topic, ((channel, schema), data) in {t: (channels[t], messages[t][0][1]) for t in channels}.items():
        if channel.message_encoding == "protobuf":
            assert schema.encoding == "protobuf", topic
            decoded = _protobuf_class(schema.name, schema.data).FromString(data)
            assert decoded.ListFields(), f"{topic}: an empty {schema.name}"
        elif channel.message_encoding in ("json", "msgpack"):
            assert schema.encoding == "jsonschema", topic
            value = json.loads(data) if channel.message_encoding == "json" else msgpack.unpackb(data, strict_map_key=False)
            jsonschema.validate(value, json.loads(schema.data), cls=jsonschema.Draft202012Validator)
        else:
            raise AssertionError(f"{topic}: message encoding {channel.message_encoding!r} is not one a viewer decodes")


def test_derived_channels_say_what_the_raw_ones_say(recording: Path, client: RobonavClient) -> None:
    messages, channels, attachments = _read(recording)
    root = client.keys.root

    def decoded(topic: str) -> list[tuple[int, Any]]:
        _channel, schema = channels[topic]
        cls = _protobuf_class(schema.name, schema.data)
        return [(t, cls.FromString(d)) for t, d in messages[topic]]

    description = RobotDescription.from_wire(messages[f"{root}/robot/description"][-1][1])
    assert [(a.name, a.media_type, a.data.decode()) for a in attachments] == [
        (f"{description.name}.urdf", "application/xml", description.urdf)]
    assert [json.loads(d) for _, d in messages[f"{root}/robot/description/urdf"]] == [{"data": description.urdf}]

    cameras = Cameras.from_wire(messages[f"{root}/cameras"][-1][1])
    transforms = decoded(f"{root}/cameras/foxglove")[-1][1].transforms
    assert [(t.parent_frame_id, t.child_frame_id) for t in transforms] == [("world", c.camera_id) for c in cameras.cameras]
    for t, camera in zip(transforms, cameras.cameras, strict=True):
        np.testing.assert_allclose([t.translation.x, t.translation.y, t.translation.z], camera.world_from_camera[:3, 3])

    # Joint states: one transform message per raw message after the description, in the same order.
    raw_states = {t: JointState.from_wire(d) for t, d in messages[f"{root}/robot/joint_states"]}
    link_frames = decoded(f"{root}/robot/joint_states/foxglove")
    assert len(link_frames) >= len(raw_states) - 50
    links = set(re.findall(r'<link name="([^"]+)"', description.urdf))
    for log_time, frames in link_frames[:: max(1, len(link_frames) // 5)]:
        state = raw_states[log_time]
        # The tree robot_state_publisher sends: world -> root link, then each joint's parent -> child.
        parent_of = {t.child_frame_id: t for t in frames.transforms}
        assert set(parent_of) == links and parent_of["panda_link0"].parent_frame_id == "world"
        assert parent_of["panda_hand"].parent_frame_id == "panda_link8"
        for link in ("panda_hand", "panda_leftfinger", "panda_link4"):
            np.testing.assert_allclose(_world_from(parent_of, link), ROBOT.frame_pose(state.position[:7], link),
                                       atol=1e-9)
    plotted = json.loads(messages[f"{root}/robot/joint_states/json"][-1][1])
    last = JointState.from_wire(messages[f"{root}/robot/joint_states"][-1][1])
    assert plotted["by_name"]["panda_joint4"]["position"] == pytest.approx(last.position[3])

    occupancy = {t: Occupancy.from_wire(d) for t, d in messages[f"{root}/perception/occupancy"]}
    for log_time, update in decoded(f"{root}/perception/occupancy/foxglove")[-3:]:
        (entity,) = update.entities
        assert len(entity.cubes) == len(occupancy[log_time].occupied_centers_m) > 0
        assert entity.cubes[0].size.x == pytest.approx(occupancy[log_time].resolution_m)

    assert any(len(u.entities) > 0 for _, u in decoded(f"{root}/perception/clusters/foxglove"))

    scenes = [{e.id: e for e in u.entities} for _, u in decoded(f"{root}/planner/scene_state/foxglove")]
    full = next(s for s in scenes if "fx_tool" in s)
    assert set(full) >= {o.name for o in OBJECTS} | {"fx_tool"}
    assert full["fx_tool"].frame_id == "panda_hand" and len(full["fx_tool"].spheres) == 1
    assert (len(full["fx_capsule"].cylinders), len(full["fx_capsule"].spheres)) == (1, 2)
    assert len(full["fx_mesh"].triangles[0].points) == 3
    assert not any(name.startswith("fx_") for name in scenes[-1]), "the removal was not recorded"

    path = ExecutorPath.from_wire(messages[f"{root}/executor/path"][-1][1])
    (line,) = decoded(f"{root}/executor/path/foxglove")[-1][1].entities[0].lines
    assert len(line.points) == len(path.path)
    ee = ROBOT.frame_pose(path.path[-1], description.end_effector_link)[:3, 3]
    np.testing.assert_allclose([line.points[-1].x, line.points[-1].y, line.points[-1].z], ee, atol=1e-9)

    states = [json.loads(d)["state"] for _, d in messages[f"{root}/executor/status/json"]]
    assert "executing" in states


def test_the_foxglove_layout_shows_channels_the_recording_has(recording: Path, client: RobonavClient) -> None:
    """docs/foxglove-layout.json (cell arm0) names only topics a recording of the stack has, and
    every plotted field is in their messages."""
    layout = json.loads((Path(__file__).resolve().parents[3] / "docs" / "foxglove-layout.json").read_text())
    messages, _, _ = _read(recording)
    panels = layout["configById"]
    scene = next(c for name, c in panels.items() if name.startswith("3D!"))
    topics = set(scene["topics"]) | {layer["topic"] for layer in scene["layers"].values() if "topic" in layer}
    paths = [p["value"] for c in panels.values() for p in c.get("paths", [])]
    paths += [c["topicPath"] for c in panels.values() if "topicPath" in c]
    assert client.keys.root == "robonav/arm0" and len(paths) > 10
    assert topics - set(messages) == set()
    for path in paths:
        topic, _, field = path.partition(".")
        assert topic in messages, path
        value = json.loads(messages[topic][-1][1])
        for part in filter(None, field.split(".")):
            assert part in value, path
            value = value[part]
