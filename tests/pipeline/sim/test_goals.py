"""Campaign goals: free, clear and in the region; detours when asked; intruders land on the path."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.planning.motion_planner import MotionPlanner, PlanProblem
from robonav.pipeline.planning.result import PlanStatus
from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.sim.goals import (
    draw_goal_sequence,
    goal_region,
    intruder_for_trajectory,
    perceivable_objects,
    point_along_path,
    sample_goal,
)
from robonav.pipeline.sim.scenes import ClutterConfig, clutter_scene
from robonav.services.config import load_config

ROBOT = RobotModel.from_config(load_config().robot)  # with the Panda's allowed-collision pairs
HOME = ROBOT.home_position_rad
REGION = (np.array([0.2, -0.6, 0.25]), np.array([0.9, 0.6, 0.9]))


def test_perceivable_objects_are_solid_down_to_the_floor() -> None:
    tilted = SceneObject("cyl", "cylinder", (0.5, 0.2, 0.4), quat_xyzw=(0.0, 0.38268, 0.0, 0.92388), radius_m=0.05,
                         length_m=0.2)
    (box,) = perceivable_objects([tilted], floor_z_m=0.0)
    center, half = box.local_bounds_m
    low, high = np.array(box.position_m) - half, np.array(box.position_m) + half
    assert low[2] == pytest.approx(0.0) and box.type == "box" and box.name == "cyl"
    # The tilted cylinder's ends reach beyond its radius in x; the box covers them.
    assert high[2] == pytest.approx(0.4 + 0.1 * 0.7071 + 0.05 * 0.7071, abs=1e-3)
    assert low[0] < 0.5 - 0.1 and high[0] > 0.5 + 0.1


@pytest.mark.parametrize("seed", range(4))
def test_sampled_goals_are_free_clear_in_the_region_and_detour_when_asked(seed: int) -> None:
    scene = clutter_scene(ClutterConfig(), np.random.default_rng((3, seed)))
    world = CollisionWorld(ROBOT, padding_m=0.05)
    world.set_objects(perceivable_objects(scene.objects, 0.0))
    rng = np.random.default_rng(seed)
    for want_blocked in (True, None):
        goal = sample_goal(world, rng, HOME, link="panda_hand", region_min_m=REGION[0], region_max_m=REGION[1],
                           min_clearance_m=0.05, want_blocked=want_blocked)
        assert goal is not None
        assert not world.in_collision(goal.q) and goal.clearance_m >= 0.05
        assert np.all(goal.link_position_m >= REGION[0]) and np.all(goal.link_position_m <= REGION[1])
        assert goal.straight_blocked == (not world.motion_valid(HOME, goal.q, 0.02))
        assert want_blocked is None or goal.straight_blocked
        assert np.max(np.abs(goal.q - HOME)) >= 0.5
    again = sample_goal(world, np.random.default_rng(seed), HOME, link="panda_hand", region_min_m=REGION[0],
                        region_max_m=REGION[1], min_clearance_m=0.05, want_blocked=True)
    first = sample_goal(world, np.random.default_rng(seed), HOME, link="panda_hand", region_min_m=REGION[0],
                        region_max_m=REGION[1], min_clearance_m=0.05, want_blocked=True)
    assert again is not None and first is not None and np.array_equal(again.q, first.q)


def test_a_continuous_joints_goal_is_drawn_on_the_turn_nearest_the_start(spinner_urdf: Path) -> None:
    urdf = spinner_urdf
    robot = RobotModel.from_config(RobotConfig(
        name="spinner", urdf=str(urdf), base_link="foot", end_effector_link="slider", joint_names=("spin", "slide"),
        max_velocity_rad_s=(2.0, 0.5), max_acceleration_rad_s2=(8.0, 2.0), max_jerk_rad_s3=(4000.0, 1000.0),
        home_position_rad=(0.0, 0.0)))
    world = CollisionWorld(robot, padding_m=0.0)
    start = np.array([3.0, 0.1])
    rng = np.random.default_rng(0)
    drawn = [sample_goal(world, rng, start, link="slider", region_min_m=[-1, -1, -1], region_max_m=[1, 1, 1],
                         min_clearance_m=0.0) for _ in range(30)]
    turns = np.array([g.q[0] for g in drawn if g is not None])
    assert len(turns) == 30
    # Uniform over the -2 pi..2 pi range, most draws would be more than half a turn away.
    assert np.all(np.abs(turns - start[0]) <= math.pi + 1e-9)
    assert np.all(turns >= robot.lower_limits_rad[0]) and np.all(turns <= robot.upper_limits_rad[0])


def test_no_goal_when_nothing_qualifies() -> None:
    world = CollisionWorld(ROBOT, padding_m=0.0)
    nowhere = sample_goal(world, np.random.default_rng(0), HOME, link="panda_hand", region_min_m=[5, 5, 5],
                          region_max_m=[6, 6, 6], min_clearance_m=0.0, attempts=50)
    assert nowhere is None


def test_points_along_a_path_follow_its_length() -> None:
    path = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 3.0]])
    np.testing.assert_allclose(point_along_path(path, 0.0), [0.0, 0.0])
    np.testing.assert_allclose(point_along_path(path, 0.25), [1.0, 0.0])
    np.testing.assert_allclose(point_along_path(path, 0.5), [1.0, 1.0])
    np.testing.assert_allclose(point_along_path(path, 2.0), [1.0, 3.0])
    np.testing.assert_allclose(point_along_path(path[:1], 0.5), [0.0, 0.0])


@pytest.mark.parametrize("goal_offset", [[2.0, 0.3, 0.0, 0.3, 0.0, -0.2, 0.0], [-2.0, 0.2, 0.3, 0.2, 0.0, 0.0, 0.3]])
def test_the_intruder_slides_in_clear_of_the_arm_and_rests_ahead_of_it(goal_offset: list[float]) -> None:
    times = np.linspace(0.0, 3.0, 61)
    # A smooth rest-to-rest motion; the box must rest 1 s before any link comes within 10 cm.
    path = HOME + (0.5 - 0.5 * np.cos(np.pi * times / 3.0))[:, None] * np.array(goal_offset)
    intruder = intruder_for_trajectory(ROBOT, times, path, link="panda_hand", slide_s=0.5, min_lead_s=1.0)
    assert intruder is not None and intruder.lead_s >= 1.0
    k = int(np.argmin(np.abs(times - intruder.target_time_s)))
    np.testing.assert_allclose(intruder.target_m, ROBOT.frame_pose(path[k], "panda_hand")[:3, 3])
    rest = intruder.start.with_pose(np.block([[np.eye(3), np.array(intruder.target_m)[:, None]], [np.zeros((1, 3)), 1.0]]))
    world = CollisionWorld(ROBOT, padding_m=0.0)
    world.set_objects([rest])
    assert world.in_collision(path[k])  # resting, the box blocks the arm's way
    threat = CollisionWorld(ROBOT, padding_m=0.1)
    threat.set_objects([rest])
    assert not any(threat.in_collision(q) for q in path[times < 0.5 + intruder.lead_s - 1e-9])
    start = np.array(intruder.start.position_m)
    near = CollisionWorld(ROBOT, padding_m=0.05)
    for t, q in zip(times[times <= 0.5], path[times <= 0.5]):  # sliding, it never comes near the arm
        pose = np.eye(4)
        pose[:3, 3] = start + (t / 0.5) * (np.array(intruder.target_m) - start)
        near.set_objects([intruder.start.with_pose(pose)])
        assert not near.in_collision(q)


def test_no_intruder_when_the_trajectory_is_too_short() -> None:
    times = np.linspace(0.0, 1.0, 21)
    path = HOME + times[:, None] * np.array([0.5, 0, 0, 0, 0, 0, 0])
    assert intruder_for_trajectory(ROBOT, times, path, link="panda_hand", slide_s=0.5, min_lead_s=1.0) is None


def test_rejected_resting_places_are_skipped_for_later_ones() -> None:
    times = np.linspace(0.0, 3.0, 61)
    path = HOME + (0.5 - 0.5 * np.cos(np.pi * times / 3.0))[:, None] * np.array([2.0, 0.3, 0.0, 0.3, 0.0, -0.2, 0.0])
    first = intruder_for_trajectory(ROBOT, times, path, link="panda_hand", slide_s=0.5, min_lead_s=1.0)
    assert first is not None
    near_first = lambda box: float(np.linalg.norm(np.array(box.position_m) - first.target_m)) < 0.05  # noqa: E731
    later = intruder_for_trajectory(ROBOT, times, path, link="panda_hand", slide_s=0.5, min_lead_s=1.0,
                                    reject=near_first)
    assert later is not None and later.target_time_s > first.target_time_s
    assert np.linalg.norm(np.array(later.target_m) - first.target_m) >= 0.05
    assert intruder_for_trajectory(ROBOT, times, path, link="panda_hand", slide_s=0.5, min_lead_s=1.0,
                                   reject=lambda box: True) is None


def test_goal_sequences_start_above_the_table_and_each_goal_is_reached_from_the_last() -> None:
    cfg = load_config()
    low, high = goal_region(cfg.sim.objects, cfg.perception.workspace_min_m, cfg.perception.workspace_max_m)
    assert low[2] == pytest.approx(0.2 + 0.05) and tuple(high) == cfg.perception.workspace_max_m  # table top 0.2 m
    world = CollisionWorld(ROBOT, padding_m=0.05)
    world.set_objects(perceivable_objects(cfg.sim.objects, 0.0))
    planner = MotionPlanner(ROBOT, world, cfg.planner)
    goals = draw_goal_sequence(world, planner, np.random.default_rng(1), HOME, count=3, link="panda_hand",
                               region_min_m=low, region_max_m=high, min_clearance_m=0.05, seed=1)
    assert len(goals) == 3
    previous = HOME
    for goal in goals:
        assert world.clearance_m(goal) >= 0.05 and np.max(np.abs(goal - previous)) >= 0.5
        assert np.all(ROBOT.frame_pose(goal, "panda_hand")[:3, 3] >= low)
        outcome = planner.plan(PlanProblem(start_rad=previous, goals_rad=goal, allowed_planning_time_s=2.0, seed=2))
        assert outcome.status is PlanStatus.SUCCESS
        previous = goal
    with pytest.raises(ValueError, match="no reachable goal 0"):  # a region the hand never reaches
        draw_goal_sequence(world, planner, np.random.default_rng(1), HOME, count=1, link="panda_hand",
                           region_min_m=[3.0, 3.0, 3.0], region_max_m=[3.1, 3.1, 3.1], min_clearance_m=0.05, seed=1,
                           draws=2)
