"""The four services over real Zenoh on loopback: plan, execute, errors, the example client."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zenoh

from robonav.pipeline.wire.messages import (
    Clusters,
    ErrorReply,
    ExecuteResponse,
    PerceptionClearResponse,
    PerceptionStatusResponse,
    PlanResponse,
    PointCloud,
    decode_reply,
)
from robonav.services.client import RobonavClient, error_reply
from robonav.services.config import load_config

from ...conftest import REPO_ROOT

pytestmark = pytest.mark.e2e

REPO = REPO_ROOT
DEFAULT = load_config()
GOALS = [np.array(g) for g in DEFAULT.demo.goals_rad]
HOME = np.array(DEFAULT.robot.home_position_rad)
# Arm folded forward and down through the table top.
IN_TABLE = np.array([0.0, 1.3, 0.0, -0.5, 0.0, 1.6, 0.785])


def _raw_plan(session: zenoh.Session, payload: bytes) -> dict:
    replies = list(session.get("robonav/arm0/planner/plan", payload=payload, timeout=10.0))
    assert len(replies) == 1
    reply = replies[0]
    sample = reply.ok if reply.ok is not None else reply.err
    raw = sample.payload.to_bytes()
    # The raw map is what is checked here, but only a structured error is one of the planner's.
    assert reply.ok is not None or error_reply(raw) is not None, f"not a structured error (Zenoh's own?): {raw[:200]!r}"
    return msgpack.unpackb(raw, raw=False) | {"_is_err": reply.ok is None}


def _move_to(client: RobonavClient, goal: np.ndarray) -> tuple[PlanResponse, str]:
    plan = client.plan(goal, allowed_planning_time=5.0, seed=1)
    assert isinstance(plan, PlanResponse), plan
    execution = client.execute(plan.path, joint_names=plan.joint_names, max_velocity_scaling_factor=1.0,
                               max_acceleration_scaling_factor=1.0)
    assert isinstance(execution, ExecuteResponse), execution
    return plan, client.wait_for_trajectory(execution.trajectory_id, execution.duration_s + 20.0)


def test_plan_and_execute_reaches_goal_without_contacts(client: RobonavClient) -> None:
    plan, result = _move_to(client, GOALS[0])
    assert result == "succeeded"
    np.testing.assert_allclose(plan.path[-1], GOALS[0], atol=1e-9)
    assert plan.path_length_rad > 0 and plan.waypoint_count == len(plan.path)
    assert plan.min_clearance_m is None or plan.min_clearance_m > 0
    assert client.wait_for(lambda: np.max(np.abs(client.joint_state.position - GOALS[0])) < 1e-3, 5.0), \
        f"arm at {client.joint_state.position}, goal {GOALS[0]}"  # type: ignore[union-attr]
    contacts = client.contacts()
    assert not isinstance(contacts, ErrorReply)
    assert contacts.contact_count == 0, contacts.pairs


@pytest.mark.parametrize(
    ("payload", "code"),
    [
        (b"\x00\xffnot msgpack at all", "MALFORMED_MESSAGE"),
        (msgpack.packb({"v": 1, "goal_positions": "up"}), "MALFORMED_MESSAGE"),
        (msgpack.packb({"v": 1, "goal_positions": {"dtype": "<f8", "shape": [7],
                                                    "data": np.array([0, 0, 0, np.nan, 0, 0, 0]).tobytes()}}),
         "INVALID_REQUEST"),
        (msgpack.packb({"v": 1, "goal_positions": {"dtype": "<f8", "shape": [3], "data": np.zeros(3).tobytes()}}),
         "INVALID_REQUEST"),
        (msgpack.packb({"v": 9, "goal_positions": {"dtype": "<f8", "shape": [7], "data": np.zeros(7).tobytes()}}),
         "UNSUPPORTED_VERSION"),
        (msgpack.packb({"v": 1, "goal_positions": {"dtype": "<f8", "shape": [7], "data": (HOME + [0, 0, 0, 3, 0, 0, 0]).tobytes()}}),
         "OUT_OF_JOINT_LIMITS"),
        (msgpack.packb({"v": 1, "goal_positions": {"dtype": "<f8", "shape": [7], "data": IN_TABLE.tobytes()}}),
         "GOAL_IN_COLLISION"),
        (msgpack.packb({"v": 1, "planner_id": "teleport", "goal_positions": {"dtype": "<f8", "shape": [7], "data": HOME.tobytes()}}),
         "UNKNOWN_PLANNER"),
    ],
    ids=["garbage", "wrong-type", "nan", "wrong-joint-count", "version", "out-of-limits", "goal-in-collision", "planner"],
)
def test_malformed_plan_request_gets_structured_error_and_planner_keeps_serving(
        client: RobonavClient, session: zenoh.Session, payload: bytes, code: str) -> None:
    reply = _raw_plan(session, payload)
    assert reply["_is_err"] and reply["ok"] is False
    assert reply["code"] == code, reply
    assert reply["message"] and isinstance(reply["details"], dict)
    assert client.alive_services() >= {"planner"}
    follow_up = client.plan(client.joint_state.position, allowed_planning_time=2.0)  # type: ignore[union-attr]
    assert isinstance(follow_up, PlanResponse), follow_up


def test_start_in_collision_names_the_pairs(client: RobonavClient) -> None:
    reply = client.plan(HOME, start_positions=IN_TABLE)
    assert isinstance(reply, ErrorReply) and reply.code == "START_IN_COLLISION"
    assert any(pair.endswith("|occupancy") for pair in reply.details["pairs"]), reply.details


@pytest.mark.parametrize(
    ("path", "code"),
    [
        (np.zeros((0, 7)), "INVALID_REQUEST"),
        (np.zeros((2, 6)), "INVALID_REQUEST"),
        (np.full((2, 7), np.nan), "INVALID_REQUEST"),
        (np.array([HOME, HOME + [0, 0, 0, 3.0, 0, 0, 0]]), "OUT_OF_JOINT_LIMITS"),
        (np.array([HOME + 0.5, HOME]), "INVALID_REQUEST"),
    ],
    ids=["empty", "wrong-joint-count", "nan", "out-of-limits", "start-far-from-state"],
)
def test_bad_execute_requests_get_structured_errors(client: RobonavClient, path: np.ndarray, code: str) -> None:
    payload = msgpack.packb({"v": 1, "path": {"dtype": "<f8", "shape": list(path.shape), "data": path.tobytes()}})
    replies = list(client.session.get("robonav/arm0/executor/execute", payload=payload, timeout=10.0))
    assert len(replies) == 1 and replies[0].err is not None
    reply = msgpack.unpackb(replies[0].err.payload.to_bytes(), raw=False)
    assert reply["code"] == code, reply


def test_example_client_plans_and_executes_with_only_zenoh_and_msgpack(client: RobonavClient, stack_config: Path) -> None:
    router = load_config(stack_config).zenoh.connect[0]
    source = (REPO / "examples" / "plan_client.py").read_text(encoding="utf-8")
    assert "robonav" not in "".join(line for line in source.splitlines() if line.startswith(("import", "from")))
    goal = GOALS[1]
    run = subprocess.run([sys.executable, str(REPO / "examples" / "plan_client.py"), "--router", router,
                          "--goal", *map(str, goal), "--execute", "--planning-time", "5"],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr + run.stdout
    assert '"result": "succeeded"' in run.stdout
    assert client.joint_state is not None
    assert client.wait_for(lambda: np.max(np.abs(client.joint_state.position - goal)) < 1e-3, 5.0)  # type: ignore[union-attr]


def _perception_status(session: zenoh.Session) -> PerceptionStatusResponse:
    replies = list(session.get("robonav/arm0/perception/status", timeout=5.0))
    assert len(replies) == 1 and replies[0].ok is not None
    status = decode_reply(replies[0].ok.payload.to_bytes(), PerceptionStatusResponse)
    assert isinstance(status, PerceptionStatusResponse)
    return status


def test_perception_survives_bad_clouds(client: RobonavClient, session: zenoh.Session) -> None:
    # Its own key, so the sim's clouds on cam0 do not replace these before they are processed.
    key = "robonav/arm0/camera/test/cloud"
    nan_points = np.full((100, 3), np.nan, dtype=np.float32)
    ones = {"dtype": "<f4", "shape": [1, 3], "data": np.ones(3, np.float32).tobytes()}
    # Out of order: older than cam0's newest frame, yet newer than any perception/clear of an
    # earlier test (a frame from before a clear is counted as before_clear instead).
    fresh = time.time()
    assert client.wait_for(lambda: client.occupancy is not None and client.occupancy.stamp > fresh, 10.0)
    older = client.occupancy.stamp - 0.01
    # Built when sent: a frame is only integrated if it is newer than the camera's last one.
    bad_payloads = [
        lambda: b"\x00garbage",
        lambda: msgpack.packb({"v": 1, "stamp": time.time(), "camera_id": "cam0", "points": "none"}),
        lambda: msgpack.packb({"v": 1, "stamp": time.time(), "camera_id": "cam0", "points": {
            "dtype": "<f4", "shape": [100, 2], "data": np.zeros(200, np.float32).tobytes()}}),
        lambda: msgpack.packb({"v": 1, "stamp": time.time(), "camera_id": "cam0", "points": {
            "dtype": "<f4", "shape": [100, 3], "data": nan_points.tobytes()}}),
        lambda: msgpack.packb({"v": 1, "stamp": time.time(), "camera_id": "cam0",
                               "points": {"dtype": "<f4", "shape": [0, 3], "data": b""}}),
        lambda: msgpack.packb({"v": 1, "stamp": time.time(), "camera_id": "nobody", "points": ones}),
        lambda: msgpack.packb({"v": 1, "stamp": older, "camera_id": "cam0", "points": ones}),
    ]
    before = _perception_status(session).dropped
    for payload in bad_payloads:
        session.put(key, payload())
        time.sleep(0.15)  # latest-only: give each its own cycle
    after = time.time()
    assert client.wait_for(lambda: client.occupancy is not None and client.occupancy.stamp > after, 10.0), \
        "perception stopped publishing maps after bad clouds"
    assert "perception" in client.alive_services()
    dropped = _perception_status(session).dropped
    grew = {reason: dropped.get(reason, 0) - before.get(reason, 0) for reason in dropped}
    assert grew.get("bad_message", 0) + grew.get("stale", 0) >= 3, dropped
    assert grew.get("empty", 0) >= 1 and grew.get("unknown_camera", 0) >= 1 and grew.get("out_of_order", 0) >= 1, dropped


def test_perception_clear_forgets_the_map_until_the_next_frame(client: RobonavClient, session: zenoh.Session) -> None:
    assert client.wait_for(lambda: client.occupancy is not None and len(client.occupancy.occupied_centers_m) > 0, 20.0)
    replies = list(session.get("robonav/arm0/perception/clear", timeout=5.0))
    assert len(replies) == 1 and replies[0].ok is not None
    cleared = decode_reply(replies[0].ok.payload.to_bytes(), PerceptionClearResponse)
    assert isinstance(cleared, PerceptionClearResponse) and cleared.cleared_voxels > 0
    # A frame taken before the clear (here: stamped 50 ms before it) shows the old world: dropped.
    before = _perception_status(session).dropped.get("before_clear", 0)
    session.put("robonav/arm0/camera/test/cloud", PointCloud(
        stamp=time.time() - 0.05, camera_id="cam0", points=np.full((10, 3), 0.5, dtype=np.float32)).to_wire())
    deadline = time.monotonic() + 10.0
    while _perception_status(session).dropped.get("before_clear", 0) == before and time.monotonic() < deadline:
        time.sleep(0.1)
    assert _perception_status(session).dropped.get("before_clear", 0) > before
    # The next camera frame maps the scene again.
    after = time.time()
    assert client.wait_for(lambda: client.occupancy is not None and client.occupancy.stamp > after
                           and len(client.occupancy.occupied_centers_m) > 0, 10.0)


def test_perception_publishes_labelled_clusters(client: RobonavClient, session: zenoh.Session) -> None:
    assert client.wait_for(lambda: client.occupancy is not None, 30.0)
    received: list[Clusters] = []
    sub = session.declare_subscriber("robonav/arm0/perception/clusters",
                                     lambda sample: received.append(Clusters.from_wire(sample.payload.to_bytes())))
    try:
        deadline = time.monotonic() + 10.0
        while not received and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        sub.undeclare()
    assert received, "no clusters published"
    clusters = received[-1]
    # The table, the pillar, the crate and the can are separate clusters.
    assert len(clusters.ids) >= 4
    assert len(clusters.labels) == len(clusters.ids)
    assert np.all(clusters.bbox_min_m <= clusters.centroids_m) and np.all(clusters.centroids_m <= clusters.bbox_max_m)


def test_joint_history_matches_cloud_stamps() -> None:
    from robonav.pipeline.wire.messages import JointState
    from robonav.services.perception.node import JointHistory

    names = DEFAULT.robot.joint_names
    history = JointHistory(names)
    assert history.nearest(1.0, max_gap_s=1.0) is None
    for stamp in (1.0, 1.01, 1.02):
        history.add(JointState(stamp=stamp, names=names, position=np.full(7, stamp), velocity=np.zeros(7)))
    history.add(JointState(stamp=0.5, names=names, position=np.zeros(7), velocity=np.zeros(7)))  # out of order: ignored
    np.testing.assert_allclose(history.nearest(1.012, max_gap_s=0.1), 1.01)
    assert history.nearest(2.0, max_gap_s=0.1) is None
    np.testing.assert_allclose(history.nearest(0.99, max_gap_s=0.1), 1.0)
