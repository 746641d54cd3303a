"""The executor state machine on a simulated clock: success, stop, busy, progress."""

import numpy as np
import pytest

from robonav.pipeline.robot_config import RobotConfig
from robonav.pipeline.trajectory.execution import ExecutionStateMachine, Limits
from robonav.pipeline.trajectory.timing import time_parameterize

ROBOT = RobotConfig()
LIMITS = Limits(np.array(ROBOT.max_velocity_rad_s), np.array(ROBOT.max_acceleration_rad_s2), np.array(ROBOT.max_jerk_rad_s3))
HOME = np.array(ROBOT.home_position_rad)
PATH = np.array([HOME, HOME + [0.6, -0.3, 0.2, 0.4, 0.0, 0.3, -0.5], HOME + [0.9, 0.0, 0.0, 0.2, 0.4, 0.0, 0.0]])


def _trajectory():  # noqa: ANN202
    return time_parameterize(PATH, max_velocity=LIMITS.velocity, max_acceleration=LIMITS.acceleration,
                             max_jerk=LIMITS.jerk, velocity_scaling=0.5, acceleration_scaling=0.5)


def test_runs_to_the_goal_then_idles_with_success() -> None:
    machine = ExecutionStateMachine(LIMITS)
    trajectory = _trajectory()
    machine.start(trajectory, "t1", now_s=10.0)
    assert machine.state == "executing" and machine.busy
    halfway = machine.status(10.0 + trajectory.duration_s / 2)
    assert halfway.progress == pytest.approx(0.5, abs=1e-6)
    last = None
    for t in np.arange(10.0, 10.0 + trajectory.duration_s + 0.01, 0.001):
        sample = machine.tick(float(t))
        if sample is None:
            break
        last = sample
    assert last is not None
    np.testing.assert_allclose(last.position, PATH[-1], atol=1e-9)
    np.testing.assert_allclose(last.velocity, 0.0, atol=1e-9)
    assert machine.state == "idle" and machine.last_result == "succeeded"
    assert machine.status(99.0).progress == 1.0
    assert machine.tick(99.0) is None


def test_stop_is_continuous_and_ends_at_rest() -> None:
    machine = ExecutionStateMachine(LIMITS)
    trajectory = _trajectory()
    machine.start(trajectory, "t2", now_s=0.0)
    t_stop = trajectory.duration_s * 0.3
    before = machine.tick(t_stop)
    assert before is not None
    machine.stop(t_stop)
    assert machine.state == "stopping"
    with pytest.raises(RuntimeError, match="stopping"):
        machine.start(trajectory, "t3", now_s=t_stop)
    after = machine.tick(t_stop)
    assert after is not None
    for a, b in ((before.position, after.position), (before.velocity, after.velocity),
                 (before.acceleration, after.acceleration)):
        np.testing.assert_allclose(a, b, atol=1e-9)
    t = t_stop
    sample = after
    while machine.busy:
        t += 0.001
        sample = machine.tick(t) or sample
        assert np.all(np.abs(sample.velocity) <= LIMITS.velocity + 1e-9)
    np.testing.assert_allclose(sample.velocity, 0.0, atol=1e-9)
    assert machine.state == "stopped" and machine.last_result == "stopped"
    machine.start(trajectory, "t4", now_s=t)  # a stopped executor takes new work
    assert machine.state == "executing"
