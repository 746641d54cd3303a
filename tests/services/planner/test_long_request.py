"""One long request (RRT* with an hour's budget) starves neither other plans nor scene changes:
the planner's second worker answers them, and the scene applies without waiting for the plan.
Requests beyond the configured limits are refused before any work."""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

from robonav.pipeline.wire.messages import ErrorReply, PlanRequest, PlanResponse, SceneObjectSpec, SceneRequest, SceneResponse
from robonav.services.client import RobonavClient
from robonav.services.common import open_session
from robonav.services.config import LimitsConfig, ZenohConfig, load_config
from robonav.services.planner.node import PlannerNode

from ..conftest import free_port

CONFIG = load_config()
GOALS = [np.array(g) for g in CONFIG.demo.goals_rad]
# The sim's obstacles as planning-scene objects: between the demo's goals stands the pillar.
OBSTACLES = tuple(SceneObjectSpec(o.name, o.type, o.position_m, o.quat_xyzw, size_m=o.size_m, radius_m=o.radius_m,
                                  length_m=o.length_m) for o in CONFIG.sim.objects)


@pytest.fixture
def planner(request: pytest.FixtureRequest) -> Iterator[tuple[PlannerNode, RobonavClient]]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohConfig(mode="router", listen=(endpoint,)))
    cfg = dataclasses.replace(CONFIG, planner=dataclasses.replace(CONFIG.planner, require_occupancy=False, workers=2),
                              limits=getattr(request, "param", CONFIG.limits))
    node_session = open_session(ZenohConfig(connect=(endpoint,)))
    node = PlannerNode(cfg, node_session)
    client_session = open_session(ZenohConfig(connect=(endpoint,)))
    client = RobonavClient(client_session)
    yield node, client
    client.close()
    node.close()
    for s in (client_session, node_session, router):
        s.close()


def test_a_second_plan_and_a_scene_change_are_answered_while_an_hour_long_plan_runs(
        planner: tuple[PlannerNode, RobonavClient]) -> None:
    node, client = planner
    assert isinstance(client.scene(SceneRequest(operation="add", objects=OBSTACLES)), SceneResponse)
    long_replies: list[PlanResponse | ErrorReply] = []
    long_request = PlanRequest(start_positions=GOALS[0], goal_positions=GOALS[1], planner_id="rrtstar",
                               allowed_planning_time=3600.0, seed=1)
    asking = threading.Thread(target=lambda: long_replies.append(client.plan_request(long_request, timeout_s=120.0)))
    asking.start()
    time.sleep(1.0)  # the long plan holds one worker now

    started = time.monotonic()
    second = client.plan_request(PlanRequest(start_positions=GOALS[0], goal_positions=GOALS[2], seed=2), timeout_s=10.0)
    second_plan_s = time.monotonic() - started
    assert isinstance(second, PlanResponse), second
    print(f"second plan answered after {second_plan_s:.3f} s while the long one runs")

    # A scene change is not held up by the plan either, and the next plan sees it.
    on_goal = node.robot.frame_pose(GOALS[2], "panda_hand")[:3, 3]
    scene = client.scene(SceneRequest(operation="add", objects=(
        SceneObjectSpec("late_box", "box", tuple(on_goal), size_m=(0.1, 0.1, 0.1)),)), timeout_s=5.0)
    assert isinstance(scene, SceneResponse) and "late_box" in [o.name for o in scene.objects], scene
    blocked = client.plan_request(PlanRequest(start_positions=GOALS[0], goal_positions=GOALS[2]), timeout_s=10.0)
    assert isinstance(blocked, ErrorReply) and blocked.code == "GOAL_IN_COLLISION", blocked
    assert asking.is_alive() and not long_replies, "the long request should still be planning"

    # Stopping the planner ends the long request with an answer: RRT*'s path so far, or none yet.
    node.stop_planning()
    asking.join(timeout=15.0)
    assert not asking.is_alive() and long_replies, "the long request did not end after stop_planning"
    last = long_replies[0]
    assert isinstance(last, PlanResponse) and last.planner_id == "rrtstar" or \
        isinstance(last, ErrorReply) and last.code == "NO_SOLUTION", last


@pytest.mark.parametrize("planner", [LimitsConfig(max_planning_time_s=10.0, max_planning_attempts=3, max_goals=2,
                                                  max_scene_objects=2, max_mesh_size=3)], indirect=True)
def test_requests_beyond_the_limits_are_refused_naming_key_value_and_limit(
        planner: tuple[PlannerNode, RobonavClient]) -> None:
    _, client = planner
    start, goal = GOALS[0], GOALS[2]
    cases = [
        (PlanRequest(start_positions=start, goal_positions=goal, allowed_planning_time=3600.0),
         {"key": "allowed_planning_time", "value": 3600.0, "limit": 10.0}),
        (PlanRequest(start_positions=start, goal_positions=goal, num_planning_attempts=4),
         {"key": "num_planning_attempts", "value": 4, "limit": 3}),
        (PlanRequest(start_positions=start, goal_set=np.array([goal, goal, goal])), {"key": "goal_set", "value": 3, "limit": 2}),
    ]
    for request, details in cases:
        reply = client.plan_request(request, timeout_s=10.0)
        assert isinstance(reply, ErrorReply) and reply.code == "INVALID_REQUEST" and reply.details == details, reply
        assert details["key"] in reply.message and "limits." in reply.message
    boxes = tuple(SceneObjectSpec(f"box{i}", "box", (2.0 + i, 0.0, 0.5), size_m=(0.1, 0.1, 0.1)) for i in range(3))
    reply = client.scene(SceneRequest(operation="add", objects=boxes))
    assert isinstance(reply, ErrorReply) and reply.details == {"key": "objects", "value": 3, "limit": 2}, reply
    # Within each request, but the scene would outgrow the limit: refused, and nothing changed.
    assert isinstance(client.scene(SceneRequest(operation="add", objects=boxes[:2])), SceneResponse)
    reply = client.scene(SceneRequest(operation="add", objects=boxes[2:]))
    assert isinstance(reply, ErrorReply) and reply.details == {"key": "objects", "value": 3, "limit": 2}, reply
    listed = client.scene(SceneRequest(operation="list"))
    assert isinstance(listed, SceneResponse) and [o.name for o in listed.objects] == ["box0", "box1"]
    mesh = SceneObjectSpec("tetra", "mesh", (2.0, 1.0, 0.5), vertices_m=np.eye(4, 3), triangles=np.array([[0, 1, 2], [0, 1, 3]]))
    reply = client.scene(SceneRequest(operation="add", objects=(mesh,)))
    assert isinstance(reply, ErrorReply) and reply.details == {"key": "objects[0].vertices_m", "value": 4, "limit": 3}, reply
