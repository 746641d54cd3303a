"""MotionPlanner for a Panda standing elsewhere (`robot.world_from_base`): obstacles and goals are in the world."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.planning.config import PlannerConfig
from robonav.pipeline.planning.ik import pose_error
from robonav.pipeline.planning.motion_planner import MotionPlanner, PlanProblem, PoseGoal
from robonav.pipeline.planning.ompl_planners import seed_ompl_once
from robonav.pipeline.planning.result import PlanStatus
from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.transforms import PoseSpec, transform_points

RESOLUTION_RAD = 0.02
# Finger pairs allowed, as in the shipped config, so both the sphere-first and the exact search run.
PANDA = RobotConfig(fixed_joint_positions={"panda_finger_joint1": 0.04, "panda_finger_joint2": 0.04},
                    allowed_collision_pairs=(("panda_leftfinger", "panda_rightfinger"), ("panda_hand", "panda_link6")))
# A quarter turn about the vertical and 0.7 m away: the robot's own frame and the world's share no axis.
POSE = PoseSpec((0.7, 0.9, 0.1), (0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4)))
# Where a block is in the way of joint 1 turning from -1 to 1 rad, in the robot's own frame.
BLOCK_IN_BASE_M = (0.307, 0.0, 0.44)


def _block(center_m: np.ndarray) -> SceneObject:
    return SceneObject("block", "box", tuple(float(v) for v in center_m), size_m=(0.08, 0.08, 0.08))


@pytest.fixture(scope="module")
def robots() -> tuple[RobotModel, RobotModel]:
    """(the Panda at the origin, the same Panda standing at POSE)."""
    seed_ompl_once(0)
    return RobotModel.from_config(PANDA), RobotModel.from_config(dataclasses.replace(PANDA, world_from_base=POSE))


def _start_goal(robot: RobotModel) -> tuple[np.ndarray, np.ndarray]:
    start, goal = robot.home_position_rad.copy(), robot.home_position_rad.copy()
    start[0], goal[0] = -1.0, 1.0
    return start, goal


def test_a_block_is_in_the_way_only_of_the_robot_it_stands_before(robots: tuple[RobotModel, RobotModel]) -> None:
    at_origin, posed = robots
    start, goal = _start_goal(posed)
    moved_block = _block(transform_points(POSE.matrix, np.array([BLOCK_IN_BASE_M]))[0])
    for robot, blocking, elsewhere in ((at_origin, _block(np.array(BLOCK_IN_BASE_M)), moved_block),
                                       (posed, moved_block, _block(np.array(BLOCK_IN_BASE_M)))):
        world = CollisionWorld(robot, padding_m=0.01)
        world.set_objects([elsewhere])
        assert world.motion_valid(start, goal, RESOLUTION_RAD), robot.config.world_from_base
        world.set_objects([blocking])
        assert not world.motion_valid(start, goal, RESOLUTION_RAD), robot.config.world_from_base


@pytest.mark.parametrize("share, search", [(1.0, "sphere_first"), (0.0, "exact")])
def test_plans_go_around_the_block_in_the_world(robots: tuple[RobotModel, RobotModel], share: float,
                                                search: str) -> None:
    _, posed = robots
    start, goal = _start_goal(posed)
    world = CollisionWorld(posed, padding_m=0.01)
    world.set_objects([_block(transform_points(POSE.matrix, np.array([BLOCK_IN_BASE_M]))[0])])
    planner = MotionPlanner(posed, world, PlannerConfig(edge_resolution_rad=RESOLUTION_RAD, range_rad=1.0,
                                                        sphere_first_share=share))
    outcome = planner.plan(PlanProblem(start, goal, allowed_planning_time_s=5.0, seed=4))
    assert outcome.status is PlanStatus.SUCCESS, outcome.detail
    assert outcome.search == search
    np.testing.assert_array_equal(outcome.path[0], start)
    np.testing.assert_array_equal(outcome.path[-1], goal)
    assert world.path_valid(outcome.path, RESOLUTION_RAD) and outcome.min_clearance_m > 0


def test_start_in_collision_and_pose_goals_are_in_the_world(robots: tuple[RobotModel, RobotModel]) -> None:
    at_origin, posed = robots
    home = posed.home_position_rad
    hand_m = posed.frame_pose(home, "panda_hand")[:3, 3]
    for robot, expected in ((at_origin, PlanStatus.SUCCESS), (posed, PlanStatus.START_INVALID)):
        world = CollisionWorld(robot, padding_m=0.01)
        world.set_objects([_block(hand_m)])
        goal = home.copy()
        goal[0] += 0.3
        outcome = MotionPlanner(robot, world, PlannerConfig()).plan(PlanProblem(home, goal, seed=1))
        assert outcome.status is expected, outcome.detail
    # A Cartesian goal of the robot at the origin, moved with the robot, is reached with the same hand pose.
    q_target = home.copy()
    q_target[0] = -0.6
    target = POSE.matrix @ at_origin.frame_pose(q_target, "panda_hand")
    world = CollisionWorld(posed, padding_m=0.01)
    outcome = MotionPlanner(posed, world, PlannerConfig()).plan(PlanProblem(home, pose_goal=PoseGoal(
        "panda_hand", target, position_tolerance_m=1e-3, orientation_tolerance_rad=0.01), seed=3))
    assert outcome.status is PlanStatus.SUCCESS, outcome.detail
    position_error_m, orientation_error_rad = pose_error(posed, outcome.path[-1], target, "panda_hand")
    assert position_error_m <= 1e-3 and orientation_error_rad <= 0.01
