"""shortcut_path and the path metrics, on random valid point-robot paths and on a Panda path."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.planning.metrics import interpolate_path, max_joint_step_rad, path_length_rad
from robonav.pipeline.planning.shortcut import shortcut_path
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject

WALLS = [(0.3, 0.0, 0.35, 0.7), (0.65, 0.3, 0.7, 1.0)]  # an S-shaped corridor


def _random_valid_path(robot, rng: np.random.Generator, waypoints: int) -> np.ndarray:
    """A random walk whose every segment passes the robot's exact segment check."""
    path = [np.array([0.1, 0.1])]
    while len(path) < waypoints:
        candidate = np.clip(path[-1] + rng.normal(0.0, 0.2, size=2), 0.0, 1.0)
        if robot.motion_valid(path[-1], candidate):
            path.append(candidate)
    return np.array(path)


# make_point_robot is a stateless factory, so reusing it across examples is safe.
@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(path_seed=st.integers(0, 2**32 - 1), shortcut_seed=st.integers(0, 2**32 - 1),
       waypoints=st.integers(2, 30), iterations=st.integers(0, 60), patience=st.integers(0, 15))
def test_shortcut_properties(make_point_robot, path_seed, shortcut_seed, waypoints, iterations, patience) -> None:
    robot = make_point_robot(WALLS)
    path = _random_valid_path(robot, np.random.default_rng(path_seed), waypoints)
    out = shortcut_path(path, motion_valid=robot.motion_valid, rng=np.random.default_rng(shortcut_seed),
                        iterations=iterations, patience=patience)
    assert out.ndim == 2 and out.shape[1] == 2 and 2 <= out.shape[0] <= path.shape[0] + 2 * iterations
    np.testing.assert_array_equal(out[0], path[0])
    np.testing.assert_array_equal(out[-1], path[-1])
    assert path_length_rad(out) <= path_length_rad(path) + 1e-12
    assert all(robot.motion_valid(a, b) for a, b in zip(out[:-1], out[1:]))
    again = shortcut_path(path, motion_valid=robot.motion_valid, rng=np.random.default_rng(shortcut_seed),
                          iterations=iterations, patience=patience)
    np.testing.assert_array_equal(out, again)


def test_shortcut_straightens_free_detour(make_point_robot) -> None:
    robot = make_point_robot([])
    path = np.array([[0.0, 0.0], [0.5, 0.9], [0.2, 0.1], [1.0, 1.0]])
    out = shortcut_path(path, motion_valid=robot.motion_valid, rng=np.random.default_rng(0), iterations=10)
    np.testing.assert_array_equal(out, [[0.0, 0.0], [1.0, 1.0]])


def test_shortcut_keeps_needed_corner(make_point_robot) -> None:
    robot = make_point_robot([(0.4, 0.0, 0.6, 0.6)])
    path = np.array([[0.1, 0.1], [0.1, 0.9], [0.9, 0.9], [0.9, 0.1]])
    out = shortcut_path(path, motion_valid=robot.motion_valid, rng=np.random.default_rng(3), iterations=200)
    assert path_length_rad(out) < path_length_rad(path) - 0.3
    assert 3 <= out.shape[0] and all(robot.motion_valid(a, b) for a, b in zip(out[:-1], out[1:]))


def test_the_first_pass_gallops_to_the_farthest_connection(make_point_robot) -> None:
    robot = make_point_robot([(0.4, 0.0, 0.6, 0.6)])
    # 17 waypoints up the left side, 16 across the top above the wall and 8 down its right side.
    path = np.vstack([np.linspace([0.1, 0.1], [0.1, 0.9], 17), np.linspace([0.15, 0.9], [0.9, 0.9], 16),
                      np.linspace([0.9, 0.8], [0.9, 0.1], 8)])
    checked: list[tuple[np.ndarray, np.ndarray]] = []

    def counted(a: np.ndarray, b: np.ndarray) -> bool:
        checked.append((a, b))
        return robot.motion_valid(a, b)

    out = shortcut_path(path, motion_valid=counted, rng=np.random.default_rng(0), iterations=0)
    assert all(robot.motion_valid(a, b) for a, b in zip(out[:-1], out[1:]))
    np.testing.assert_array_equal(out[[0, -1]], path[[0, -1]])
    # One corner above the wall stays: trying each next waypoint in turn took a check per
    # waypoint (40 in all); galloping and bisecting take a few per kept one (14).
    assert 3 <= out.shape[0] <= 5
    assert len(checked) <= 25
    dropped = shortcut_path(np.repeat(path[:3], 2, axis=0), motion_valid=robot.motion_valid,
                            rng=np.random.default_rng(0), iterations=0)
    np.testing.assert_array_equal(dropped, path[[0, 2]])  # duplicate waypoints go, the ends stay


def test_patience_stops_when_nothing_shortens(make_point_robot) -> None:
    robot = make_point_robot([(0.4, 0.0, 0.6, 0.95)])
    path = np.array([[0.1, 0.1], [0.1, 0.97], [0.9, 0.97], [0.9, 0.1]])  # the corners are needed
    calls = {0: 0, 5: 0}
    for patience in calls:
        def counted(a: np.ndarray, b: np.ndarray, patience: int = patience) -> bool:
            calls[patience] += 1
            return robot.motion_valid(a, b)
        out = shortcut_path(path, motion_valid=counted, rng=np.random.default_rng(1), iterations=300, patience=patience)
        assert all(robot.motion_valid(a, b) for a, b in zip(out[:-1], out[1:]))
    assert calls[5] < calls[0] / 5
    with pytest.raises(ValueError, match="patience"):
        shortcut_path(path, motion_valid=robot.motion_valid, rng=np.random.default_rng(1), iterations=3, patience=-1)


def test_shortcut_panda_path(panda: RobotModel) -> None:
    world = CollisionWorld(panda, padding_m=0.01)
    world.set_objects([SceneObject("block", "box", (0.307, 0.0, 0.44), size_m=(0.08, 0.08, 0.08))])
    start, goal = panda.home_position_rad.copy(), panda.home_position_rad.copy()
    start[0], goal[0] = -1.0, 1.0
    lifted = [start.copy(), start.copy(), goal.copy(), goal.copy()]
    lifted[1][1] = lifted[2][1] = -1.4
    path = interpolate_path(np.array(lifted), 0.3)
    assert world.path_valid(path, 0.02)
    out = shortcut_path(path, motion_valid=lambda a, b: world.motion_valid(a, b, 0.02),
                        rng=np.random.default_rng(0), iterations=30)
    assert path_length_rad(out) < path_length_rad(path)
    assert world.path_valid(out, 0.02)
    np.testing.assert_array_equal(out[[0, -1]], path[[0, -1]])


def test_metrics() -> None:
    path = np.array([[0.0, 0.0], [3.0, 4.0], [3.0, 5.0]])
    assert path_length_rad(path) == pytest.approx(6.0)
    assert max_joint_step_rad(path) == pytest.approx(4.0)
    assert max_joint_step_rad(path[:1]) == 0.0
    dense = interpolate_path(path, 0.5)
    assert max_joint_step_rad(dense) <= 0.5 + 1e-12
    assert path_length_rad(dense) == pytest.approx(6.0)
    np.testing.assert_array_equal(dense[[0, -1]], path[[0, -1]])
    for waypoint in path:
        assert np.any(np.all(np.isclose(dense, waypoint), axis=1))
    assert dense.shape == (1 + 8 + 2, 2)
    with pytest.raises(ValueError, match=r"path\[1, 0\] must be finite"):
        path_length_rad(np.array([[0.0, 0.0], [np.nan, 1.0]]))
    with pytest.raises(ValueError, match="max_step_rad"):
        interpolate_path(path, 0.0)
