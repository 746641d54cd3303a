"""The executor's path monitor on the live stack: a box dropped onto the path mid-motion.

The sim adds the box where the hand will pass later (at least `LEAD_S` after it appears), so
the camera, perception and the monitor have time to see it; the arm must stop, and with
`replan` reach the goal on a new path, without touching anything.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.sim.goals import intruder_for_trajectory, perceivable_objects
from robonav.pipeline.trajectory.timing import time_parameterize
from robonav.pipeline.wire.messages import (
    ErrorReply,
    ExecuteResponse,
    ExecutorStatus,
    PerceptionClearRequest,
    PerceptionClearResponse,
    PlanResponse,
    SimObjectsRequest,
    SimObjectsResponse,
)
from robonav.services.client import RobonavClient
from robonav.services.config import load_config
from robonav.services.planner.scene_specs import object_spec

from ..conftest import plan_and_execute

pytestmark = pytest.mark.e2e

DEFAULT = load_config()
# The base swings the arm, hand high and out, from one side of the table to the other: long
# enough at 30 % speed to drop a box ahead of the hand, and free of the stack's obstacles.
LEFT = np.array([-1.3, 0.0, 0.0, -1.2, 0.0, 1.9, 0.785])
RIGHT = np.array([1.3, 0.0, 0.0, -1.2, 0.0, 1.9, 0.785])
SCALING = 0.3
TABLE_TOP_M = 0.2
LEAD_S = 1.5
"""The box rests this long before any link comes within 10 cm of it: a 5 Hz camera frame, the
map, the monitor's check and a stop fit well inside."""


def _objects(client: RobonavClient, request: SimObjectsRequest) -> SimObjectsResponse:
    reply = client.query(client.keys.sim_objects, request, SimObjectsResponse, 10.0)
    assert not isinstance(reply, ErrorReply), reply
    return reply


def _move(client: RobonavClient, goal: np.ndarray) -> None:
    assert plan_and_execute(client, goal, seed=3) == "succeeded"


def _drop_box_on_the_way(client: RobonavClient, goal: np.ndarray, *, replan: bool,
                         trajectory_id: str) -> tuple[ExecutorStatus, np.ndarray]:
    """Plan to `goal`, execute, drop a box on the path as it starts; returns the final status
    of the trajectory and the planned path."""
    robot = RobotModel.from_config(DEFAULT.robot)
    plan = client.plan(goal, allowed_planning_time=5.0, seed=4)
    assert isinstance(plan, PlanResponse), plan
    trajectory = time_parameterize(plan.path, max_velocity=robot.velocity_limits,
                                   max_acceleration=robot.acceleration_limits, max_jerk=robot.jerk_limits,
                                   velocity_scaling=SCALING, acceleration_scaling=SCALING,
                                   max_path_deviation_rad=DEFAULT.executor.max_path_deviation_rad)
    times, q, _, _ = trajectory.sample_uniform(0.05)
    # Perception fills below what it sees, so the box stands for a column down to the table:
    # keep that column off the goal, or no replan could reach it.
    seen_as = CollisionWorld(robot, padding_m=DEFAULT.robot.padding_m + DEFAULT.perception.inflation_m
                             + DEFAULT.perception.resolution_m)

    def blocks_goal(box: SceneObject) -> bool:
        seen_as.set_objects(perceivable_objects([box], TABLE_TOP_M))
        return seen_as.in_collision(goal)

    intruder = intruder_for_trajectory(robot, times, q, link=DEFAULT.robot.end_effector_link, slide_s=0.0,
                                       min_lead_s=LEAD_S, name="dropped", reject=blocks_goal)
    assert intruder is not None, "the path is too short to drop a box on it in time"
    box = intruder.start.with_pose(np.block([[np.eye(3), np.array(intruder.target_m)[:, None]], [np.zeros((1, 3)), 1.0]]))
    assert client.contacts(reset=True) is not None
    execution = client.execute(plan.path, joint_names=plan.joint_names, trajectory_id=trajectory_id, replan=replan,
                               max_velocity_scaling_factor=SCALING, max_acceleration_scaling_factor=SCALING)
    assert isinstance(execution, ExecuteResponse), execution
    _objects(client, SimObjectsRequest(operation="add", objects=(object_spec(box),)))
    try:
        client.wait_for_trajectory(trajectory_id, 60.0)
        status = client.status
        assert status is not None and status.trajectory_id == trajectory_id
        contacts = client.contacts()
        assert not isinstance(contacts, ErrorReply)
        assert contacts.contact_count == 0, contacts.pairs
    finally:
        _objects(client, SimObjectsRequest(operation="remove", names=("dropped",)))
        # Later tests share the stack: its map must not keep the box. Frames rendered before the
        # removal may still be on their way (the sim's latency model): clear after they are in.
        time.sleep(1.0)
        cleared_at = time.time()
        cleared = client.query(client.keys.perception_clear, PerceptionClearRequest(), PerceptionClearResponse, 5.0)
        assert isinstance(cleared, PerceptionClearResponse), cleared
        # Render workers may still show the box in a frame or two after its removal: wait until
        # the map has nothing left where it was.
        low, high = np.array(intruder.target_m) - 0.08, np.array(intruder.target_m) + 0.08

        def box_forgotten() -> bool:
            occupancy = client.occupancy
            if occupancy is None or occupancy.stamp <= cleared_at:
                return False
            centers = occupancy.occupied_centers_m
            return not np.any(np.all((centers >= low) & (centers <= high), axis=1))

        assert client.wait_for(box_forgotten, 10.0), "the removed box stays in the map"
    return status, plan.path


def test_a_box_on_the_path_stops_the_arm_and_a_replan_reaches_the_goal(client: RobonavClient) -> None:
    _move(client, LEFT)
    status, _ = _drop_box_on_the_way(client, RIGHT, replan=True, trajectory_id="replan-test")
    assert (status.state, status.last_result) == ("idle", "succeeded"), status
    assert status.replans >= 1
    assert status.blocked_after_frame_s is not None and status.blocked_after_frame_s > 0
    assert client.wait_for(lambda: np.max(np.abs(client.joint_state.position - RIGHT)) < 1e-3, 5.0)  # type: ignore[union-attr]


def test_without_replan_the_arm_stops_short_with_path_blocked(client: RobonavClient) -> None:
    _move(client, LEFT)
    status, _ = _drop_box_on_the_way(client, RIGHT, replan=False, trajectory_id="block-test")
    assert (status.state, status.error_code) == ("error", "PATH_BLOCKED"), status
    assert status.replans == 0
    time.sleep(0.2)
    assert np.max(np.abs(client.joint_state.position - RIGHT)) > 0.3  # type: ignore[union-attr]
