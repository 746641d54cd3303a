"""Continuous joints in a plan: the goal's equivalent angle nearest the start is where the path
ends, so the joint turns the short way, and the path's metrics measure that turn."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.planning.config import PlannerConfig
from robonav.pipeline.planning.motion_planner import MotionPlanner, PlanProblem, PoseGoal
from robonav.pipeline.planning.result import PlanStatus
from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject

TURN = 2.0 * math.pi
RESOLUTION_RAD = 0.02

# A carriage lifted on a prismatic joint, an arm turning on it without end (continuous).
URDF = """<?xml version="1.0"?>
<robot name="lift_spin">
  <link name="base"><collision><origin xyz="0 0 0.05"/><geometry><box size="0.2 0.2 0.1"/></geometry></collision></link>
  <link name="carriage"><collision><geometry><box size="0.1 0.1 0.06"/></geometry></collision></link>
  <link name="arm"><collision><origin xyz="0.2 0 0"/><geometry><box size="0.4 0.05 0.05"/></geometry></collision></link>
  <link name="tool"/>
  <joint name="lift" type="prismatic"><parent link="base"/><child link="carriage"/><origin xyz="0 0 0.3"/>
    <axis xyz="0 0 1"/><limit lower="0.0" upper="0.5" effort="10" velocity="0.25"/></joint>
  <joint name="spin" type="continuous"><parent link="carriage"/><child link="arm"/><origin xyz="0 0 0.1"/>
    <axis xyz="0 0 1"/><limit effort="10" velocity="2.0"/></joint>
  <joint name="tool_joint" type="fixed"><parent link="arm"/><child link="tool"/><origin xyz="0.45 0 0"/></joint>
</robot>
"""


@pytest.fixture(scope="module")
def robot(tmp_path_factory: pytest.TempPathFactory) -> RobotModel:
    urdf = tmp_path_factory.mktemp("lift_spin") / "robot.urdf"
    urdf.write_text(URDF, encoding="utf-8")
    return RobotModel.from_config(RobotConfig(
        name="lift_spin", urdf=str(urdf), base_link="base", end_effector_link="tool", joint_names=("lift", "spin"),
        max_velocity_rad_s=(0.25, 2.0), max_acceleration_rad_s2=(1.0, 8.0), max_jerk_rad_s3=(500.0, 4000.0),
        home_position_rad=(0.1, 0.0)))


def _planner(robot: RobotModel, objects: list[SceneObject] | None = None) -> tuple[MotionPlanner, CollisionWorld]:
    world = CollisionWorld(robot)
    world.set_objects(objects or [])
    return MotionPlanner(robot, world, PlannerConfig(edge_resolution_rad=RESOLUTION_RAD)), world


def test_a_continuous_joint_turns_the_short_way_and_the_path_ends_there(robot: RobotModel) -> None:
    assert robot.continuous_mask.tolist() == [False, True]
    planner, world = _planner(robot)
    outcome = planner.plan(PlanProblem(start_rad=np.array([0.1, 3.0]), goals_rad=np.array([0.1, -3.0]), seed=1))
    assert outcome.status is PlanStatus.SUCCESS, outcome.detail
    assert outcome.path is not None
    short = TURN - 6.0  # 0.283 rad across +-pi, not 6 rad back through 0
    np.testing.assert_allclose(outcome.path[-1], [0.1, -3.0 + TURN], atol=1e-12)
    assert outcome.path_length_rad == pytest.approx(short, abs=1e-9)
    assert outcome.max_joint_step_rad == pytest.approx(short, abs=1e-9)
    assert np.all(outcome.path <= robot.upper_limits_rad) and np.all(outcome.path >= robot.lower_limits_rad)
    # The same pose as the goal asked for: the arm's tool is where -3.0 rad puts it.
    np.testing.assert_allclose(robot.frame_pose(outcome.path[-1], "tool"), robot.frame_pose(np.array([0.1, -3.0]), "tool"),
                               atol=1e-9)
    assert world.path_valid(outcome.path, RESOLUTION_RAD)


def test_goals_outside_the_range_and_goal_sets_wrap_to_the_start(robot: RobotModel) -> None:
    planner, _ = _planner(robot)
    # 7 rad is beyond the planned range (2 pi): its equivalent 0.717 rad is not.
    beyond = planner.plan(PlanProblem(start_rad=np.array([0.1, 0.0]), goals_rad=np.array([0.1, 7.0]), seed=1))
    assert beyond.status is PlanStatus.SUCCESS, beyond.detail
    assert beyond.path is not None and beyond.path[-1, 1] == pytest.approx(7.0 - TURN)
    # Near the upper bound, 0.5 + 2 pi lies outside: the nearest equivalent inside is 0.5 itself.
    edge = planner.plan(PlanProblem(start_rad=np.array([0.1, 6.0]), goals_rad=np.array([0.1, 0.5]), seed=1))
    assert edge.path is not None and edge.path[-1, 1] == pytest.approx(0.5)
    # Each goal of a set wraps on its own; `goal_index` still names the row asked for.
    goal_set = np.array([[0.3, 2.0], [0.1, -3.0]])
    outcome = planner.plan(PlanProblem(start_rad=np.array([0.1, 3.0]), goals_rad=goal_set, seed=1))
    assert outcome.status is PlanStatus.SUCCESS and outcome.path is not None
    assert outcome.goal_index == 0 and outcome.path[-1, 1] == pytest.approx(2.0)
    blocked_first = planner.plan(PlanProblem(start_rad=np.array([0.1, 3.0]), goals_rad=goal_set[::-1], seed=1))
    assert blocked_first.path is not None and blocked_first.goal_index == 0
    assert blocked_first.path[-1, 1] == pytest.approx(-3.0 + TURN)


def test_the_short_way_blocked_the_path_still_ends_at_the_nearest_equivalent(robot: RobotModel) -> None:
    # A low post at -x (angle pi), in the way of the short turn from -2.5 to 2.5 rad (-> -3.78).
    post = SceneObject("post", "box", (-0.4, 0.0, 0.3), size_m=(0.08, 0.08, 0.4))
    planner, world = _planner(robot, [post])
    start, goal = np.array([0.1, -2.5]), np.array([0.1, 2.5])
    wrapped = np.array([0.1, 2.5 - TURN])
    assert not world.in_collision(start) and not world.in_collision(goal)
    assert world.motion_valid(start, goal, RESOLUTION_RAD), "the long way round is free"
    assert not world.motion_valid(start, wrapped, RESOLUTION_RAD), "the short way hits the post"
    outcome = planner.plan(PlanProblem(start_rad=start, goals_rad=goal, allowed_planning_time_s=5.0, seed=1))
    assert outcome.status is PlanStatus.SUCCESS, outcome.detail
    assert outcome.path is not None and world.path_valid(outcome.path, RESOLUTION_RAD)
    np.testing.assert_allclose(outcome.path[-1], wrapped, atol=1e-12)
    # The arm's padded underside (0.4 + lift - 0.035 m) clears the post's top (0.5 m) above a 0.135 m lift.
    assert outcome.path[:, 0].max() > 0.13, "the carriage rose over the post"
    np.testing.assert_allclose(outcome.path_length_rad, np.sum(np.linalg.norm(np.diff(outcome.path, axis=0), axis=1)))
    assert outcome.path_length_rad < 5.0, "not the 5 rad long way round"


def test_an_ik_solution_is_taken_on_the_turn_nearest_the_start(robot: RobotModel) -> None:
    planner, _ = _planner(robot)
    target = robot.frame_pose(np.array([0.2, -3.0]), "tool")
    outcome = planner.plan(PlanProblem(start_rad=np.array([0.1, 3.0]), pose_goal=PoseGoal("tool", target), seed=2))
    assert outcome.status is PlanStatus.SUCCESS, outcome.detail
    assert outcome.path is not None
    np.testing.assert_allclose(outcome.path[-1], [0.2, -3.0 + TURN], atol=1e-3)
    assert outcome.path_length_rad < 0.5
