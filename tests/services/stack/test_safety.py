"""No command drives the arm into what the map holds, on the live stack (real sim, perception,
planner and executor processes): an execute through the pillar is refused with or without the
plan's map stamp, and a plan and execute right after `perception/clear` wait for the map."""

from __future__ import annotations

import time

import numpy as np
import pytest

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.wire.messages import (
    ErrorReply,
    ExecuteResponse,
    PerceptionClearRequest,
    PerceptionClearResponse,
    PlanResponse,
    SceneObjectSpec,
    SceneRequest,
    SceneResponse,
)
from robonav.services.client import RobonavClient
from robonav.services.config import load_config

pytestmark = pytest.mark.e2e

DEFAULT = load_config()
GOALS = [np.array(g) for g in DEFAULT.demo.goals_rad]
ROBOT = RobotModel.from_config(DEFAULT.robot)


def _truth() -> CollisionWorld:
    world = CollisionWorld(ROBOT, padding_m=0.0)
    world.set_objects(DEFAULT.sim.objects)
    return world


def _move_to(client: RobonavClient, goal: np.ndarray) -> None:
    for attempt in range(3):
        plan = client.plan(goal, allowed_planning_time=5.0, seed=11 + attempt)
        assert isinstance(plan, PlanResponse), plan
        execution = client.execute(plan.path, joint_names=plan.joint_names, replan=True)
        if isinstance(execution, ErrorReply) and execution.code == "PATH_IN_COLLISION":
            continue  # a voxel came in after the plan: plan again
        assert isinstance(execution, ExecuteResponse), execution
        assert client.wait_for_trajectory(execution.trajectory_id, execution.duration_s + 20.0) == "succeeded"
        return
    raise AssertionError("no plan to the goal survived the execute check three times")


def _position(client: RobonavClient) -> np.ndarray:
    assert client.joint_state is not None
    return client.joint_state.position.copy()


def test_an_execute_through_the_pillar_is_refused_with_or_without_a_stamp(client: RobonavClient) -> None:
    _move_to(client, GOALS[0])
    start = _position(client)
    through = np.array([start, GOALS[1]])
    assert not _truth().motion_valid(start, GOALS[1], 0.01), "the straight line must pass through an obstacle"
    assert not isinstance(client.contacts(reset=True), ErrorReply)
    assert client.occupancy is not None
    for stamp in (None, client.occupancy.stamp):
        reply = client.execute(through, occupancy_stamp=stamp)
        assert isinstance(reply, ErrorReply) and reply.code == "PATH_IN_COLLISION", reply
        assert reply.details["index"] > 0 and reply.details["time_from_start_s"] > 0
        assert any(pair.endswith("|occupancy") for pair in reply.details["pairs"]), reply.details
    time.sleep(0.3)
    assert np.max(np.abs(_position(client) - start)) < 1e-3, "the arm moved"
    contacts = client.contacts()
    assert not isinstance(contacts, ErrorReply) and contacts.contact_count == 0, contacts


def test_an_execute_through_a_planner_object_is_refused(client: RobonavClient) -> None:
    """The executor knows the planner's scene objects (planner/scene_state), not only the map."""
    _move_to(client, np.array(DEFAULT.robot.home_position_rad))
    start = _position(client)
    # A swing of the base clear of the scene, with the object early on it: the first state that
    # collides meets the object, nothing else.
    clear_of_scene = CollisionWorld(ROBOT, padding_m=0.05)
    clear_of_scene.set_objects(DEFAULT.sim.objects)
    swing = next(d for d in (0.3, -0.3, 0.6, -0.6) if clear_of_scene.motion_valid(start, start + d * np.eye(7)[0], 0.01))
    goal = start + swing * np.eye(7)[0]
    midway = ROBOT.frame_pose(start + 0.3 * swing * np.eye(7)[0], "panda_hand")[:3, 3]
    added = client.scene(SceneRequest(operation="add", objects=(
        SceneObjectSpec("keep_out", "box", tuple(midway), size_m=(0.08, 0.08, 0.08)),)))
    assert isinstance(added, SceneResponse), added
    try:
        # The planner replies before its scene reaches the executor: the execute names the revision.
        reply = client.execute(np.array([_position(client), goal]), scene_revision=added.revision)
        assert isinstance(reply, ErrorReply) and reply.code == "PATH_IN_COLLISION", reply
        assert any(pair.endswith("|keep_out") for pair in reply.details["pairs"]), reply.details
        assert reply.details["scene_revision"] == added.revision
    finally:
        removed = client.scene(SceneRequest(operation="remove", names=("keep_out",)))
        assert isinstance(removed, SceneResponse), removed


def test_plan_and_execute_right_after_a_clear_wait_for_the_map(client: RobonavClient) -> None:
    """After perception/clear the map is empty, not free: an execute through the pillar is still
    refused, and a plan is made only on the rebuilt map, then executed without a contact."""
    _move_to(client, GOALS[0])
    start = _position(client)
    assert not isinstance(client.contacts(reset=True), ErrorReply)
    cleared_at = time.time()
    cleared = client.query(client.keys.perception_clear, PerceptionClearRequest(), PerceptionClearResponse, 5.0)
    assert isinstance(cleared, PerceptionClearResponse) and cleared.cleared_voxels > 0
    refused = client.execute(np.array([start, GOALS[1]]))
    assert isinstance(refused, ErrorReply) and refused.code in ("OCCUPANCY_INCOMPLETE", "PATH_IN_COLLISION"), refused
    plan = None
    deadline = time.monotonic() + 20.0
    while plan is None and time.monotonic() < deadline:
        reply = client.plan(GOALS[1], allowed_planning_time=5.0, seed=5)
        if isinstance(reply, ErrorReply):
            assert reply.code == "OCCUPANCY_INCOMPLETE", reply  # the only acceptable refusal: retry
            continue
        plan = reply
    assert isinstance(plan, PlanResponse), "no plan within 20 s of the clear"
    assert plan.occupancy_stamp > cleared_at, "planned on a map that does not show the world after the clear"
    assert _truth().path_valid(plan.path, 0.01), "the plan made on the rebuilt map passes through an obstacle"
    execution = client.execute(plan.path, joint_names=plan.joint_names, replan=True)
    assert isinstance(execution, ExecuteResponse), execution
    assert client.wait_for_trajectory(execution.trajectory_id, execution.duration_s + 20.0) == "succeeded"
    contacts = client.contacts()
    assert not isinstance(contacts, ErrorReply) and contacts.contact_count == 0, contacts
