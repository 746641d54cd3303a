"""Sampling a trajectory on a stream's grid: one row per period, ending at rest at the goal."""

import math

import numpy as np

from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.trajectory.setpoint_table import sample_table
from robonav.pipeline.trajectory.timing import time_parameterize

ROBOT = RobotConfig()
HOME = np.array(ROBOT.home_position_rad)
PERIOD_S = 1e-3


def _trajectory():
    return time_parameterize(np.array([HOME, HOME + 0.3]), max_velocity=ROBOT.max_velocity_rad_s,
                             max_acceleration=ROBOT.max_acceleration_rad_s2, max_jerk=ROBOT.max_jerk_rad_s3,
                             velocity_scaling=0.5, acceleration_scaling=0.5)


def test_rows_cover_the_trajectory_and_end_at_rest_at_the_goal() -> None:
    trajectory = _trajectory()
    table = sample_table(trajectory, "t", 12.5, PERIOD_S)
    rows = math.ceil(trajectory.duration_s / PERIOD_S - 1e-9) + 1
    assert table.complete and table.position.shape == (rows, HOME.size) == table.acceleration.shape
    assert table.trajectory_id == "t" and table.start_s == 12.5
    np.testing.assert_allclose(table.position[0], HOME, atol=1e-12)
    np.testing.assert_allclose(table.position[-1], HOME + 0.3, atol=1e-9)
    np.testing.assert_allclose(table.velocity[-1], 0.0, atol=1e-9)
    k = rows // 2
    q, qd, qdd = trajectory.sample(k * PERIOD_S)
    np.testing.assert_allclose((table.position[k], table.velocity[k], table.acceleration[k]), (q, qd, qdd))


def test_a_head_is_the_first_rows_and_says_it_is_incomplete() -> None:
    trajectory = _trajectory()
    whole = sample_table(trajectory, "t", 0.0, PERIOD_S)
    head = sample_table(trajectory, "t", 0.0, PERIOD_S, max_rows=100)
    assert not head.complete and head.position.shape[0] == 100
    np.testing.assert_array_equal(head.position, whole.position[:100])
    short = sample_table(trajectory, "t", 0.0, PERIOD_S, max_rows=whole.position.shape[0])
    assert short.complete
