"""plan_lattice (A*, Dijkstra, weighted A*) on a 2-D point robot and on the Panda with a real CollisionWorld."""

from __future__ import annotations

import numpy as np
import pytest

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.planning.baselines.lattice import plan_lattice
from robonav.pipeline.planning.result import PlanStatus
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject

WALL = (0.45, 0.0, 0.55, 0.8)  # x0, y0, x1, y1: a wall with a gap above it
START, GOAL = np.array([0.1, 0.1]), np.array([0.9, 0.13])  # the goal is off the lattice


def _plan(robot, start=START, goal=GOAL, *, resolution_rad=0.05, heuristic_weight=1.0, time_limit_s=5.0,
          max_expansions=1_000_000):
    return plan_lattice(start, goal, lower_rad=robot.lower, upper_rad=robot.upper, is_valid=robot.is_valid,
                        motion_valid=robot.motion_valid, resolution_rad=resolution_rad,
                        heuristic_weight=heuristic_weight, time_limit_s=time_limit_s, max_expansions=max_expansions)


def _l1_length(path: np.ndarray) -> float:
    return float(np.sum(np.abs(np.diff(path, axis=0))))


def _assert_valid_path(robot, path: np.ndarray, start: np.ndarray, goal: np.ndarray) -> None:
    np.testing.assert_array_equal(path[0], start)
    np.testing.assert_array_equal(path[-1], goal)
    assert all(robot.motion_valid(a, b) for a, b in zip(path[:-1], path[1:]))
    assert np.all(path >= robot.lower) and np.all(path <= robot.upper)


def test_path_around_wall_on_the_lattice(make_point_robot) -> None:
    robot = make_point_robot([WALL])
    result = _plan(robot)
    assert result.status is PlanStatus.SUCCESS, result.detail
    path = result.path
    assert path.shape[1] == 2 and path.shape[0] >= 3
    _assert_valid_path(robot, path, START, GOAL)
    assert np.max(path[:, 1]) > 0.8  # over the wall
    # Every waypoint but the goal is a lattice node, one joint moved by one step at a time.
    k = (path[:-1] - START) / 0.05
    np.testing.assert_allclose(k, np.round(k), atol=1e-9)
    steps = np.abs(np.diff(path[:-1], axis=0))
    np.testing.assert_allclose(np.sort(steps, axis=1), np.tile([0.0, 0.05], (len(steps), 1)), atol=1e-9)
    assert np.max(np.abs(path[-2] - GOAL)) <= 0.05 + 1e-12


@pytest.mark.parametrize("walls", [[WALL], [WALL, (0.2, 0.3, 0.3, 1.0), (0.7, 0.2, 0.8, 1.0)]])
def test_astar_is_as_short_as_dijkstra(make_point_robot, walls) -> None:
    robot = make_point_robot(walls)
    dijkstra = _plan(robot, resolution_rad=0.02, heuristic_weight=0.0)
    astar = _plan(robot, resolution_rad=0.02, heuristic_weight=1.0)
    weighted = _plan(robot, resolution_rad=0.02, heuristic_weight=3.0)
    for result in (dijkstra, astar, weighted):
        assert result.status is PlanStatus.SUCCESS, result.detail
        _assert_valid_path(robot, result.path, START, GOAL)
    # A consistent heuristic keeps A* optimal on the lattice; weighted A* is at most `weight` times longer.
    assert _l1_length(astar.path) == pytest.approx(_l1_length(dijkstra.path), abs=1e-9)
    assert _l1_length(dijkstra.path) <= _l1_length(weighted.path) + 1e-9 <= 3.0 * _l1_length(dijkstra.path)


def test_thin_wall_between_lattice_nodes_is_not_crossed(make_point_robot) -> None:
    # Lattice x values are 0.1 + 0.05 k: the wall lies strictly between x = 0.45 and x = 0.5, so
    # every node is valid and only the (lazily checked) edges can see it.
    robot = make_point_robot([(0.47, 0.0, 0.48, 0.8)])
    result = _plan(robot)
    assert result.status is PlanStatus.SUCCESS, result.detail
    _assert_valid_path(robot, result.path, START, GOAL)
    assert np.max(result.path[:, 1]) > 0.8


def test_direct_segment_when_free(make_point_robot) -> None:
    result = _plan(make_point_robot([]))
    assert result.status is PlanStatus.SUCCESS
    np.testing.assert_array_equal(result.path, [START, GOAL])


def test_enclosed_goal_exhausts_the_lattice(make_point_robot) -> None:
    robot = make_point_robot([(0.7, 0.0, 0.72, 0.3), (0.7, 0.28, 1.0, 0.3)])  # with the square's edges
    result = _plan(robot, resolution_rad=0.05)
    assert result.status is PlanStatus.TIMEOUT and result.path is None
    assert "reachable nodes expanded" in result.detail


def test_tiny_budgets_time_out_cleanly(make_point_robot) -> None:
    robot = make_point_robot([WALL])
    result = _plan(robot, resolution_rad=0.01, max_expansions=5)
    assert result.status is PlanStatus.TIMEOUT and result.path is None and "5 expansions" in result.detail
    result = _plan(robot, resolution_rad=0.001, time_limit_s=0.05)
    assert result.status is PlanStatus.TIMEOUT and result.path is None
    assert 0.05 <= result.planning_time_s < 0.5


def test_invalid_start_goal_and_bounds(make_point_robot) -> None:
    robot = make_point_robot([WALL])
    assert _plan(robot, start=np.array([0.5, 0.5])).status is PlanStatus.START_INVALID
    assert _plan(robot, goal=np.array([0.5, 0.5])).status is PlanStatus.GOAL_INVALID
    result = _plan(robot, goal=np.array([0.9, 1.2]))
    assert result.status is PlanStatus.OUT_OF_BOUNDS and result.path is None
    assert "goal" in result.detail and "joint 1" in result.detail


def test_bad_input_raises(make_point_robot) -> None:
    robot = make_point_robot([])
    with pytest.raises(ValueError, match=r"q_goal must have shape \(2,\)"):
        _plan(robot, goal=np.zeros(3))
    with pytest.raises(ValueError, match=r"q_start\[1\] must be finite"):
        _plan(robot, start=np.array([0.1, np.nan]))
    with pytest.raises(ValueError, match="resolution_rad"):
        _plan(robot, resolution_rad=0.0)
    with pytest.raises(ValueError, match="heuristic_weight"):
        _plan(robot, heuristic_weight=-1.0)
    with pytest.raises(ValueError, match="time_limit_s"):
        _plan(robot, time_limit_s=float("inf"))
    with pytest.raises(ValueError, match="max_expansions"):
        _plan(robot, max_expansions=0)
    with pytest.raises(ValueError, match=r"lower_rad\[0\]"):
        plan_lattice(START, GOAL, lower_rad=np.ones(2), upper_rad=np.ones(2), is_valid=robot.is_valid,
                     motion_valid=robot.motion_valid, resolution_rad=0.1)


@pytest.fixture(scope="module")
def panda_world(panda: RobotModel) -> CollisionWorld:
    return CollisionWorld(panda, padding_m=0.01)


def _panda_plan(panda: RobotModel, world: CollisionWorld, start, goal, **kwargs):
    return plan_lattice(start, goal, lower_rad=panda.lower_limits_rad, upper_rad=panda.upper_limits_rad,
                        is_valid=lambda q: not world.in_collision(q),
                        motion_valid=lambda a, b: world.motion_valid(a, b, 0.02), **kwargs)


def test_panda_easy_detour(panda: RobotModel, panda_world: CollisionWorld) -> None:
    panda_world.set_objects([SceneObject("block", "box", (0.307, 0.0, 0.44), size_m=(0.08, 0.08, 0.08))])
    start, goal = panda.home_position_rad.copy(), panda.home_position_rad.copy()
    start[0], goal[0] = -1.0, 1.0
    assert not panda_world.motion_valid(start, goal, 0.02)
    result = _panda_plan(panda, panda_world, start, goal, resolution_rad=0.1, time_limit_s=10.0)
    assert result.status is PlanStatus.SUCCESS, result.detail
    np.testing.assert_array_equal(result.path[0], start)
    np.testing.assert_array_equal(result.path[-1], goal)
    assert panda_world.path_valid(result.path, 0.02)
    assert all(panda.check_joint_limits(q) == [] for q in result.path)


def test_panda_hard_problem_times_out_cleanly(panda: RobotModel, panda_world: CollisionWorld) -> None:
    # A tall pillar on the hand's circle: A* needs thousands of expansions (seconds), so 0.2 s is too little.
    panda_world.set_objects([SceneObject("pillar", "cylinder", (0.31, 0.0, 0.6), radius_m=0.08, length_m=1.2)])
    start, goal = panda.home_position_rad.copy(), panda.home_position_rad.copy()
    start[0], goal[0] = -1.0, 1.0
    result = _panda_plan(panda, panda_world, start, goal, resolution_rad=0.1, time_limit_s=0.2)
    assert result.status is PlanStatus.TIMEOUT and result.path is None
    assert "0.200 s" in result.detail
    assert 0.2 <= result.planning_time_s < 1.0
