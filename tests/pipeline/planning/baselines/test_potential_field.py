"""plan_potential_field on a 2-D point robot (open space, wall, U-shaped trap) and on the Panda."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence

import numpy as np
import pytest

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.planning.baselines.potential_field import PotentialFieldConfig, plan_potential_field
from robonav.pipeline.planning.result import PlanStatus
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject

START, GOAL = np.array([0.1, 0.5]), np.array([0.9, 0.5])
U_TRAP = ((0.6, 0.25, 0.62, 0.75), (0.4, 0.25, 0.62, 0.27), (0.4, 0.73, 0.62, 0.75))
"""A cup open towards the start, its bottom across the straight line to the goal."""
CONFIG_2D = PotentialFieldConfig(step_rad=0.01, goal_tolerance_rad=0.02, influence_distance_m=0.1)


def _box_clearance(walls: Sequence[tuple[float, float, float, float]]) -> Callable[[np.ndarray], float]:
    """Euclidean distance from the point to the nearest closed box (0 inside), +inf without boxes."""

    def clearance(q: np.ndarray) -> float:
        best = math.inf
        for x0, y0, x1, y1 in walls:
            dx = max(x0 - q[0], 0.0, q[0] - x1)
            dy = max(y0 - q[1], 0.0, q[1] - y1)
            best = min(best, math.hypot(dx, dy))
        return best

    return clearance


def _plan(robot, config=CONFIG_2D, *, start=START, goal=GOAL, seed=0):
    return plan_potential_field(start, goal, lower_rad=robot.lower, upper_rad=robot.upper, is_valid=robot.is_valid,
                                motion_valid=robot.motion_valid, clearance_m=_box_clearance(robot.walls),
                                rng=np.random.default_rng(seed), config=config)


def _assert_valid_path(robot, path: np.ndarray, start: np.ndarray, goal: np.ndarray) -> None:
    np.testing.assert_array_equal(path[0], start)
    np.testing.assert_array_equal(path[-1], goal)
    assert all(robot.motion_valid(a, b) for a, b in zip(path[:-1], path[1:]))
    assert np.all(path >= robot.lower) and np.all(path <= robot.upper)


def test_box_clearance_helper() -> None:
    clearance = _box_clearance([(0.4, 0.4, 0.6, 0.6)])
    assert clearance(np.array([0.5, 0.5])) == 0.0
    assert clearance(np.array([0.3, 0.5])) == pytest.approx(0.1)
    assert clearance(np.array([0.7, 0.7])) == pytest.approx(math.sqrt(0.02))
    assert _box_clearance([])(np.array([0.5, 0.5])) == math.inf


def test_open_space_reaches_goal(make_point_robot) -> None:
    robot = make_point_robot([])
    result = _plan(robot)
    assert result.status is PlanStatus.SUCCESS, result.detail
    _assert_valid_path(robot, result.path, START, GOAL)
    steps = np.linalg.norm(np.diff(result.path, axis=0), axis=1)
    assert np.all(steps[:-1] <= CONFIG_2D.step_rad + 1e-12)
    assert steps[-1] <= max(CONFIG_2D.step_rad, CONFIG_2D.goal_tolerance_rad) + 1e-12  # the goal segment
    # Straight down the attractive gradient: no detour.
    assert np.sum(steps) == pytest.approx(np.linalg.norm(GOAL - START), rel=1e-6)


def test_slides_around_an_obstacle_off_the_line(make_point_robot) -> None:
    robot = make_point_robot([(0.45, 0.35, 0.55, 0.48)])  # below the straight line, within the influence
    result = _plan(robot)
    assert result.status is PlanStatus.SUCCESS, result.detail
    _assert_valid_path(robot, result.path, START, GOAL)
    assert min(_box_clearance(robot.walls)(q) for q in result.path) > 0.0
    assert np.max(result.path[:, 1]) > 0.5  # pushed up, away from the box


@pytest.mark.parametrize("walls", [[(0.45, 0.3, 0.55, 0.7)], list(U_TRAP)], ids=["wall", "u_trap"])
def test_local_minimum_without_random_walk(make_point_robot, walls) -> None:
    robot = make_point_robot(walls)
    result = _plan(robot)
    assert result.status is PlanStatus.TIMEOUT and result.path is None
    assert result.detail.startswith("local minimum at"), result.detail
    assert "0 random-walk escape(s)" in result.detail
    assert result.planning_time_s < 0.5


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_walk_escapes_u_trap(make_point_robot, seed: int) -> None:
    robot = make_point_robot(list(U_TRAP))
    result = _plan(robot, dataclasses.replace(CONFIG_2D, max_escapes=8, escape_step_rad=0.1), seed=seed)
    assert result.status is PlanStatus.SUCCESS, result.detail
    _assert_valid_path(robot, result.path, START, GOAL)
    assert "0 random-walk" not in result.detail


def test_escape_budget_is_bounded(make_point_robot) -> None:
    robot = make_point_robot(list(U_TRAP))
    # Walks too short to leave the cup: every escape ends in the same minimum.
    config = dataclasses.replace(CONFIG_2D, max_escapes=2, escape_steps=2, escape_step_rad=0.01)
    result = _plan(robot, config)
    assert result.status is PlanStatus.TIMEOUT and result.detail.startswith("local minimum at")
    assert "2 random-walk escape(s)" in result.detail


def test_same_seed_same_path(make_point_robot) -> None:
    robot = make_point_robot(list(U_TRAP))
    config = dataclasses.replace(CONFIG_2D, max_escapes=8)
    a, b = _plan(robot, config, seed=5), _plan(robot, config, seed=5)
    assert a.status is b.status
    np.testing.assert_array_equal(a.path, b.path)


def test_step_budget_times_out(make_point_robot) -> None:
    result = _plan(make_point_robot([]), dataclasses.replace(CONFIG_2D, max_steps=10))
    assert result.status is PlanStatus.TIMEOUT and "budget" in result.detail


def test_invalid_start_goal_and_bounds(make_point_robot) -> None:
    robot = make_point_robot([(0.45, 0.3, 0.55, 0.7)])
    assert _plan(robot, start=np.array([0.5, 0.5])).status is PlanStatus.START_INVALID
    assert _plan(robot, goal=np.array([0.5, 0.5])).status is PlanStatus.GOAL_INVALID
    result = _plan(robot, goal=np.array([1.2, 0.5]))
    assert result.status is PlanStatus.OUT_OF_BOUNDS and "goal" in result.detail and "joint 0" in result.detail


def test_bad_input_raises(make_point_robot) -> None:
    robot = make_point_robot([])
    with pytest.raises(ValueError, match=r"q_goal must have shape \(2,\)"):
        _plan(robot, goal=np.zeros(3))
    with pytest.raises(ValueError, match=r"q_start\[0\] must be finite"):
        _plan(robot, start=np.array([np.inf, 0.5]))
    with pytest.raises(ValueError, match="step_rad"):
        PotentialFieldConfig(step_rad=0.0)
    with pytest.raises(ValueError, match="repulsive_gain"):
        PotentialFieldConfig(repulsive_gain=-1.0)
    with pytest.raises(ValueError, match="influence_distance_m"):
        PotentialFieldConfig(influence_distance_m=float("nan"))
    with pytest.raises(ValueError, match="max_escapes"):
        PotentialFieldConfig(max_escapes=-1)
    with pytest.raises(ValueError, match="stall_window"):
        PotentialFieldConfig(stall_window=1)


def test_panda_slides_past_a_block(panda: RobotModel) -> None:
    world = CollisionWorld(panda, padding_m=0.01)
    world.set_objects([SceneObject("block", "box", (0.307, 0.0, 0.44), size_m=(0.08, 0.08, 0.08))])
    start, goal = panda.home_position_rad.copy(), panda.home_position_rad.copy()
    start[0], goal[0] = -1.0, 1.0
    assert not world.motion_valid(start, goal, 0.02)
    result = plan_potential_field(
        start, goal, lower_rad=panda.lower_limits_rad, upper_rad=panda.upper_limits_rad,
        is_valid=lambda q: not world.in_collision(q), motion_valid=lambda a, b: world.motion_valid(a, b, 0.02),
        clearance_m=world.clearance_m, rng=np.random.default_rng(0),
        config=PotentialFieldConfig(step_rad=0.05, influence_distance_m=0.15, time_limit_s=10.0),
    )
    assert result.status is PlanStatus.SUCCESS, result.detail
    np.testing.assert_array_equal(result.path[0], start)
    np.testing.assert_array_equal(result.path[-1], goal)
    assert world.path_valid(result.path, 0.02)
    assert world.path_clearance_m(result.path, 0.05) > 0.0
    assert all(panda.check_joint_limits(q) == [] for q in result.path)
