"""Codec round trips for every message, and structured errors for malformed payloads."""

from __future__ import annotations

import dataclasses

import msgpack
import numpy as np
import pytest

from robonav.pipeline.camera import CameraIntrinsics
from robonav.pipeline.wire.codec import SCHEMA_VERSION, Message, ProtocolError
from robonav.pipeline.wire.codes import ErrorCode
from robonav.pipeline.wire.messages import (
    ALL_MESSAGES,
    AttachedObjectSpec,
    CameraDescription,
    Cameras,
    CameraStats,
    ContactEvent,
    ContactsRequest,
    ContactsResponse,
    DepthImage,
    ErrorReply,
    ExecuteRequest,
    ExecuteResponse,
    ExecutorStatus,
    JointState,
    ObjectMotionSpec,
    Occupancy,
    PlanningSceneState,
    PlanRequest,
    PlanResponse,
    PointCloud,
    RobotDescription,
    SceneObjectSpec,
    SceneObjectState,
    SceneRequest,
    SceneResponse,
    ServiceProcessStatus,
    Setpoint,
    SimObjectsRequest,
    SimObjectsResponse,
    SimStatsRequest,
    SimStatsResponse,
    StackStatusRequest,
    StackStatusResponse,
    StopRequest,
    StopResponse,
    decode_reply,
)

RNG = np.random.default_rng(7)
NAMES = tuple(f"j{i}" for i in range(7))

EXAMPLES: list[Message] = [
    JointState(stamp=1.5, names=NAMES, position=RNG.normal(size=7), velocity=RNG.normal(size=7)),
    PointCloud(stamp=2.0, camera_id="cam0", points=RNG.normal(size=(50, 3)).astype(np.float32), seq=3,
               intrinsics=CameraIntrinsics(640, 480, 430.0, 430.0, 319.5, 239.5)),
    Occupancy(stamp=3.0, resolution_m=0.02, octomap_binary=b"# Octomap OcTree binary file\n\x00\xff",
              occupied_centers_m=RNG.normal(size=(10, 3)).astype(np.float32), seq=2, camera_frames={"cam0": 3, "cam1": 0}),
    PlanRequest(goal_positions=RNG.normal(size=7), joint_names=NAMES, start_positions=RNG.normal(size=7),
                planner_id="rrtconnect", allowed_planning_time=1.0, seed=4, simplify=False,
                max_velocity_scaling_factor=0.3, max_acceleration_scaling_factor=0.2, request_id="r1"),
    PlanRequest(goal_positions=RNG.normal(size=7)),
    PlanResponse(joint_names=NAMES, path=RNG.normal(size=(4, 7)), planning_time_s=0.01, path_length_rad=2.0,
                 min_clearance_m=None, waypoint_count=4, request_id="r1"),
    ExecuteRequest(path=RNG.normal(size=(3, 7)), joint_names=NAMES, max_velocity_scaling_factor=0.5, trajectory_id="t"),
    ExecuteResponse(trajectory_id="t", duration_s=2.5, waypoint_count=3),
    StopRequest(emergency=True),
    StopResponse(state="stopping"),
    Setpoint(stamp=4.0, trajectory_id="t", names=NAMES, position=RNG.normal(size=7), velocity=RNG.normal(size=7),
             acceleration=RNG.normal(size=7)),
    ExecutorStatus(stamp=5.0, state="executing", trajectory_id="t", progress=0.5, time_from_start_s=1.0, duration_s=2.0),
    ContactsRequest(reset=True),
    ContactsResponse(contact_count=2, pairs=("panda_hand|box",), min_distance_m=0.01),
    ErrorReply(code="NO_SOLUTION", message="no path in 1.0 s", details={"time_s": 1.0}),
    SceneRequest(operation="add", objects=(
        SceneObjectSpec("box", "box", (0.5, 0.0, 0.2), (0.0, 0.0, 0.0, 1.0), size_m=(0.1, 0.2, 0.3)),
        SceneObjectSpec("tet", "mesh", (0.4, 0.1, 0.0), vertices_m=RNG.normal(size=(4, 3)),
                        triangles=np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]]), frame_id="world"),
    ), request_id="s1"),
    SceneRequest(operation="attach", names=("box",), link="panda_hand", touch_links=("panda_leftfinger",),
                 joint_names=NAMES, joint_positions=RNG.normal(size=7)),
    SceneResponse(revision=3, objects=(
        SceneObjectState("box", "box", (0.5, 0.0, 0.2), (0.0, 0.0, 0.0, 1.0), size_m=(0.1, 0.2, 0.3)),
        SceneObjectState("can", "cylinder", (0.0, 0.0, 0.1), (0.0, 0.0, 0.0, 1.0), frame_id="panda_hand",
                         attached_link="panda_hand", touch_links=("panda_leftfinger",), radius_m=0.03, length_m=0.1),
    ), request_id="s1"),
    PlanRequest(goal_set=RNG.normal(size=(3, 7)), goal_tolerance_rad=0.01, num_planning_attempts=2, planner_id="auto"),
    PlanRequest(goal_position_m=np.array([0.4, 0.1, 0.5]), goal_quat_xyzw=np.array([1.0, 0.0, 0.0, 0.0]),
                goal_link="panda_hand", position_tolerance_m=0.002, orientation_tolerance_rad=0.05,
                workspace_min_m=np.array([-1.0, -1.0, 0.0]), workspace_max_m=np.array([1.0, 1.0, 1.5])),
    PlanResponse(joint_names=NAMES, path=RNG.normal(size=(2, 7)), planner_id="direct", goal_index=2,
                 goal_positions=RNG.normal(size=7)),
    PointCloud(stamp=2.5, camera_id="cam1", points=RNG.normal(size=(4, 3)).astype(np.float32),
               labels=np.array([0, 2, -1, 2], dtype=np.int32), label_names={0: "robot", 2: "crate"}),
    DepthImage(stamp=2.6, camera_id="cam1", intrinsics=CameraIntrinsics(4, 2, 3.0, 3.0, 1.5, 0.5),
               depth_m=np.array([[1.0, np.inf, np.inf, 2.0], [0.5, 0.6, 0.7, 0.8]], dtype=np.float32), seq=9,
               labels=np.array([[1, -1, -1, 0], [1, 1, 1, 1]], dtype=np.int32), label_names={0: "robot", 1: "box"}),
    ContactEvent(stamp=6.0, link="panda_hand", object="box", event="begin", distance_m=-0.002, contact_count=1),
    SimObjectsRequest(operation="script", motions=(
        ObjectMotionSpec("box", position_m=(0.5, 0.0, 0.4), duration_s=1.0, at_progress=0.3, trajectory_id="t"),
        ObjectMotionSpec("can", action="add", at_s=2.0,
                         object=SceneObjectSpec("can", "cylinder", (0.4, 0.2, 0.3), radius_m=0.05, length_m=0.2)),
    ), request_id="o1"),
    SimObjectsRequest(operation="set", objects=(SceneObjectSpec("box", "box", (0.5, 0.0, 0.2), size_m=(0.1, 0.2, 0.3)),)),
    SimObjectsResponse(stamp=7.0, sim_time_s=3.5, revision=2, objects=(
        SceneObjectState("box", "box", (0.5, 0.0, 0.2), (0.0, 0.0, 0.0, 1.0), size_m=(0.1, 0.2, 0.3)),),
        pending_motions=1, fired_motions=1, request_id="o1"),
    PlanningSceneState(stamp=8.0, revision=3, objects=(
        SceneObjectSpec("tet", "mesh", (0.4, 0.1, 0.0), vertices_m=RNG.normal(size=(4, 3)),
                        triangles=np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]])),), attached=(
        AttachedObjectSpec(link="panda_hand", touch_links=("panda_leftfinger",),
                           object=SceneObjectSpec("cup", "cylinder", (0.0, 0.0, 0.1), radius_m=0.04, length_m=0.1,
                                                  frame_id="panda_hand")),)),
    SimStatsRequest(reset=True),
    SimStatsResponse(wall_time_s=10.0, sim_time_s=9.99, real_time_factor=0.999, steps=2398, step_lateness_ms_p50=0.1,
                     step_lateness_ms_p99=4.0, step_lateness_ms_max=20.0, dropped_time_s=0.0,
                     joint_state_period_ms_max=30.0, cameras=(CameraStats("cam0", frames=50, render_ms_p50=90.0),),
                     driver_state="holding", setpoints_followed=1200, setpoints_rejected={"jump": 2, "velocity": 0},
                     setpoint_timeouts=1, brakes=3, last_rejection="jump: joint 0 position is 0.5 from ..."),
    StackStatusRequest(),
    StackStatusResponse(stamp=8.0, started_stamp=1.0, supervisor_pid=42, restart=True, services=(
        ServiceProcessStatus("planner", "running", True, restarts=1, pid=43, uptime_s=3.5, alive_for_s=1.0,
                             last_exit_code=-9, last_exit_stamp=4.0, last_back_s=2.5),
        ServiceProcessStatus("sim", "restarting", False, restarts=2, last_exit_code=1, restart_in_s=1.0),
    )),
    RobotDescription(stamp=9.0, name="panda", urdf="<robot name='panda'/>", base_frame="panda_link0",
                     end_effector_link="panda_hand", joint_names=NAMES, lower_limits=-np.ones(7), upper_limits=np.ones(7),
                     max_velocity=np.full(7, 2.0), max_acceleration=np.full(7, 10.0), max_jerk=np.full(7, 5000.0),
                     home_position=np.zeros(7), fixed_joint_positions={"panda_finger_joint1": 0.04},
                     allowed_collision_pairs=("panda_hand|panda_leftfinger",), padding_m=0.01),
    Cameras(stamp=10.0, cameras=(CameraDescription("cam0", CameraIntrinsics(640, 480, 430.0, 430.0, 319.5, 239.5),
                                                   world_from_camera=np.eye(4), output="both", near_m=0.1, far_m=3.0,
                                                   rate_hz=5.0),)),
]


def _equal(a: object, b: object) -> bool:
    if isinstance(a, np.ndarray):
        return isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b)
    return a == b


def test_every_message_has_an_example() -> None:
    assert {type(m) for m in EXAMPLES} == set(ALL_MESSAGES)


@pytest.mark.parametrize("message", EXAMPLES, ids=lambda m: type(m).__name__)
def test_round_trip(message: Message) -> None:
    decoded = type(message).from_wire(message.to_wire())
    for f in dataclasses.fields(message):  # type: ignore[arg-type]
        assert _equal(getattr(message, f.name), getattr(decoded, f.name)), f.name


@pytest.mark.parametrize("message", EXAMPLES, ids=lambda m: type(m).__name__)
def test_wire_form_is_plain_msgpack(message: Message) -> None:
    """What other languages see: a map with v, snake_case keys and array maps."""
    obj = msgpack.unpackb(message.to_wire(), raw=False)
    assert obj["v"] == SCHEMA_VERSION
    assert all(k == k.lower() and " " not in k for k in obj)
    for value in obj.values():
        if isinstance(value, dict) and "dtype" in value:
            assert value["dtype"] in ("<f4", "<f8", "<i4")
            assert len(value["data"]) == int(np.prod(value["shape"])) * int(value["dtype"][-1])


def test_float64_points_are_accepted_and_converted() -> None:
    pts = RNG.normal(size=(5, 3))
    obj = {"v": 1, "stamp": 1.0, "camera_id": "c", "points": {"dtype": "<f8", "shape": [5, 3], "data": pts.tobytes()}}
    cloud = PointCloud.from_wire(msgpack.packb(obj, use_bin_type=True))
    assert cloud.points.dtype == np.float32 and np.allclose(cloud.points, pts, atol=1e-6)


def _plan_obj(**overrides: object) -> bytes:
    obj: dict[str, object] = {"v": 1, "goal_positions": {"dtype": "<f8", "shape": [7], "data": np.zeros(7).tobytes()}}
    obj.update(overrides)
    return msgpack.packb(obj, use_bin_type=True)


@pytest.mark.parametrize(
    ("payload", "code", "fragment"),
    [
        (b"\xc1garbage", ErrorCode.MALFORMED_MESSAGE, "not valid msgpack"),
        (msgpack.packb([1, 2, 3]), ErrorCode.MALFORMED_MESSAGE, "expected a map"),
        (msgpack.packb({"goal_positions": 1}), ErrorCode.MALFORMED_MESSAGE, "missing schema version"),
        (_plan_obj(v=2), ErrorCode.UNSUPPORTED_VERSION, "schema version 2"),
        (_plan_obj(planer_id="x"), ErrorCode.MALFORMED_MESSAGE, "unknown key 'planer_id'"),
        (msgpack.packb({"v": 1}), ErrorCode.INVALID_REQUEST, "exactly one of goal_positions, goal_set, goal_position_m"),
        (_plan_obj(goal_position_m={"dtype": "<f8", "shape": [3], "data": np.zeros(3).tobytes()}),
         ErrorCode.INVALID_REQUEST, "got goal_positions, goal_position_m"),
        (msgpack.packb({"v": 1, "goal_set": {"dtype": "<f8", "shape": [1, 7], "data": np.zeros(7).tobytes()},
                        "goal_quat_xyzw": {"dtype": "<f8", "shape": [4], "data": np.array([0, 0, 0, 1.0]).tobytes()}}),
         ErrorCode.INVALID_REQUEST, "'goal_quat_xyzw' belongs to a Cartesian goal"),
        (_plan_obj(num_planning_attempts=0), ErrorCode.INVALID_REQUEST, "num_planning_attempts must be >= 1"),
        (_plan_obj(goal_positions=[0.0] * 7), ErrorCode.MALFORMED_MESSAGE, "array map"),
        (_plan_obj(goal_positions={"dtype": "<f8", "shape": [7], "data": b"\x00" * 8}), ErrorCode.MALFORMED_MESSAGE, "data bytes"),
        (_plan_obj(goal_positions={"dtype": "<f8", "shape": [7, 1], "data": np.zeros(7).tobytes()}), ErrorCode.INVALID_REQUEST, "shape"),
        (_plan_obj(goal_positions={"dtype": ">f8", "shape": [7], "data": np.zeros(7).tobytes()}), ErrorCode.MALFORMED_MESSAGE, "dtype"),
        (_plan_obj(goal_positions={"dtype": "<f8", "shape": [2], "data": np.array([0.0, np.nan]).tobytes()}),
         ErrorCode.INVALID_REQUEST, "non-finite value at index \\[1\\]"),
        (_plan_obj(allowed_planning_time="soon"), ErrorCode.MALFORMED_MESSAGE, "must be a number"),
        (_plan_obj(allowed_planning_time=float("inf")), ErrorCode.INVALID_REQUEST, "must be finite"),
        (_plan_obj(allowed_planning_time=-1.0), ErrorCode.INVALID_REQUEST, "must be > 0"),
        (_plan_obj(max_velocity_scaling_factor=1.5), ErrorCode.INVALID_REQUEST, "in \\(0, 1\\]"),
        (_plan_obj(joint_names=["a", "b"]), ErrorCode.INVALID_REQUEST, "7 joint values but 2 joint names"),
        (_plan_obj(seed=True), ErrorCode.MALFORMED_MESSAGE, "must be an integer"),
    ],
)
def test_malformed_plan_requests_raise_structured_errors(payload: bytes, code: ErrorCode, fragment: str) -> None:
    with pytest.raises(ProtocolError, match=fragment) as info:
        PlanRequest.from_wire(payload)
    assert info.value.code is code


def test_decode_reply_tells_errors_from_results() -> None:
    error = ErrorReply(code="START_IN_COLLISION", message="x", details={"pairs": ["a|b"]})
    assert isinstance(decode_reply(error.to_wire(), PlanResponse), ErrorReply)
    assert isinstance(decode_reply(EXAMPLES[5].to_wire(), PlanResponse), PlanResponse)


def test_error_codes_are_a_closed_list() -> None:
    with pytest.raises(ValueError):
        ErrorReply(code="SOMETHING_ELSE", message="x")
    assert {c.value for c in ErrorCode} >= {"START_IN_COLLISION", "GOAL_IN_COLLISION", "NO_SOLUTION", "INVALID_REQUEST"}


def test_cloud_labels_must_match_points_and_name_integer_labels() -> None:
    points = {"dtype": "<f4", "shape": [2, 3], "data": np.zeros(6, np.float32).tobytes()}
    base = {"v": 1, "stamp": 1.0, "camera_id": "c", "points": points}
    with pytest.raises(ProtocolError, match="labels has shape") as info:
        PointCloud.from_wire(msgpack.packb(base | {"labels": {"dtype": "<i4", "shape": [3],
                                                              "data": np.zeros(3, np.int32).tobytes()}}))
    assert info.value.code is ErrorCode.INVALID_REQUEST
    with pytest.raises(ProtocolError, match="integer labels"):
        PointCloud.from_wire(msgpack.packb(base | {"label_names": {"box": "box"}}))
    cloud = PointCloud.from_wire(msgpack.packb(base | {"label_names": {"3": "box"}}))
    assert cloud.label_names == {3: "box"} and cloud.labels is None
    with pytest.raises(ValueError, match="intrinsics say"):
        DepthImage(stamp=1.0, camera_id="c", intrinsics=CameraIntrinsics(4, 2, 1.0, 1.0, 1.5, 0.5),
                   depth_m=np.zeros((4, 2), np.float32))
