"""The executor state machine on a simulated clock: success, stop, busy, progress."""

import numpy as np
import pytest

from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.trajectory.config import ExecutorConfig
from robonav.pipeline.trajectory.execution import ExecutionStateMachine, Limits
from robonav.pipeline.trajectory.timing import time_parameterize
from robonav.pipeline.wire.codes import ErrorCode

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
    revision = machine.revision
    machine.stop(t_stop)
    assert machine.state == "stopping"
    # The stop ramp is a new trajectory from t_stop: whoever streams it must hear of it.
    assert machine.revision == revision + 1 and machine.started_at_s == t_stop
    assert machine.trajectory is not None and machine.trajectory is not trajectory
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


def _run(machine: ExecutionStateMachine, t0: float, t1: float, dt: float = 0.001) -> list:  # noqa: ANN401
    samples = []
    for t in np.arange(t0, t1, dt):
        sample = machine.tick(float(t))
        if sample is not None:
            samples.append(sample)
    return samples


def _assert_continuous(before, after) -> None:  # noqa: ANN001
    for a, b in ((before.position, after.position), (before.velocity, after.velocity),
                 (before.acceleration, after.acceleration)):
        np.testing.assert_allclose(a, b, atol=1e-9)


def _assert_within(samples: list, scale: float, dt: float = 0.001) -> None:
    qd = np.array([s.velocity for s in samples])
    qdd = np.array([s.acceleration for s in samples])
    assert np.all(np.abs(qd) <= LIMITS.velocity * scale + 1e-6)
    assert np.all(np.abs(qdd) <= LIMITS.acceleration * scale + 1e-6)
    assert np.all(np.abs(np.diff(qdd, axis=0)) / dt <= LIMITS.jerk * scale * (1 + 1e-6) + 1e-6)


def test_preemption_blends_from_the_commanded_state() -> None:
    machine = ExecutionStateMachine(LIMITS)
    first = _trajectory()
    machine.start(first, "a", now_s=0.0)
    t_switch = 0.4 * first.duration_s
    before = machine.tick(t_switch)
    assert before is not None and np.abs(before.velocity).max() > 0.1
    q = before.position
    new_path = np.array([q, q + [0.3, 0.2, -0.2, 0.1, 0.0, 0.0, 0.2], q + [0.1, 0.4, 0.0, 0.3, 0.1, 0.0, 0.0]])
    second = time_parameterize(new_path, max_velocity=LIMITS.velocity, max_acceleration=LIMITS.acceleration,
                               max_jerk=LIMITS.jerk, velocity_scaling=0.5, acceleration_scaling=0.5)
    assert machine.start(second, "b", now_s=t_switch) is True
    after = machine.tick(t_switch)
    assert after is not None and after.trajectory_id == "b"
    _assert_continuous(before, after)
    samples = [before, after, *_run(machine, t_switch + 0.001, t_switch + 30.0)]
    _assert_within(samples, 0.5)
    assert machine.state == "idle" and machine.last_result == "succeeded"
    np.testing.assert_array_equal(samples[-1].position, new_path[-1])


def test_a_motion_from_rest_stands_at_its_start_for_the_dwell_and_a_preemption_does_not() -> None:
    machine = ExecutionStateMachine(LIMITS)
    trajectory = _trajectory()
    machine.start(trajectory, "a", now_s=5.0, start_dwell_s=0.1)
    assert machine.status(5.0).duration_s == pytest.approx(trajectory.duration_s + 0.1)
    for t in (5.0, 5.05, 5.1 - 1e-9):
        sample = machine.tick(t)
        assert sample is not None
        np.testing.assert_array_equal(sample.position, PATH[0])
        assert not np.any(sample.velocity) and not np.any(sample.acceleration)
    for offset_s in (0.0, 0.01, 0.3):  # then the motion, on its own time
        sample = machine.tick(5.1 + offset_s)
        assert sample is not None
        for got, want in zip((sample.position, sample.velocity, sample.acceleration), trajectory.sample(offset_s)):
            np.testing.assert_allclose(got, want, atol=1e-12)
    waypoint_times = machine.trajectory.waypoint_times_s  # type: ignore[union-attr]
    np.testing.assert_allclose(waypoint_times, trajectory.waypoint_times_s + 0.1)  # type: ignore[operator]
    moving = machine.tick(5.5)
    assert moving is not None and np.abs(moving.velocity).max() > 0.1
    assert machine.start(trajectory, "b", now_s=5.5, start_dwell_s=0.1) is True  # a blend: no standing still
    after = machine.tick(5.5)
    assert after is not None
    _assert_continuous(moving, after)
    with pytest.raises(ValueError, match="dwell_s"):
        ExecutionStateMachine(LIMITS).start(trajectory, "c", now_s=0.0, start_dwell_s=-0.1)


def test_a_delayed_start_moves_the_machines_clock_with_it() -> None:
    machine = ExecutionStateMachine(LIMITS)
    trajectory = _trajectory()
    machine.start(trajectory, "late", now_s=10.0)
    machine.delay(0.25)
    assert machine.started_at_s == 10.25
    for t in (0.0, 0.3 * trajectory.duration_s, 0.7 * trajectory.duration_s):
        commanded = machine.commanded_state(10.25 + t)
        assert commanded is not None
        for got, want in zip(commanded, trajectory.sample(t)):
            np.testing.assert_allclose(got, want, atol=1e-9)
    assert machine.status(10.25 + trajectory.duration_s / 2).progress == pytest.approx(0.5, abs=1e-6)
    # A stop now brakes from where the delayed motion is, not from where it would have been.
    machine.stop(10.25 + 0.5 * trajectory.duration_s)
    stopped = machine.commanded_state(10.25 + 0.5 * trajectory.duration_s)
    assert stopped is not None
    np.testing.assert_allclose(stopped[0], trajectory.sample(0.5 * trajectory.duration_s)[0], atol=1e-9)


@pytest.mark.parametrize("emergency", [False, True])
def test_stop_is_jerk_limited_and_continuous(emergency: bool) -> None:
    machine = ExecutionStateMachine(LIMITS)
    trajectory = _trajectory()
    machine.start(trajectory, "s", now_s=0.0)
    t_stop = 0.5 * trajectory.duration_s
    before = machine.tick(t_stop)
    machine.stop(t_stop, emergency=emergency)
    after = machine.tick(t_stop)
    _assert_continuous(before, after)
    samples = [before, after, *_run(machine, t_stop + 0.001, t_stop + 5.0)]
    _assert_within(samples, 1.0 if emergency else 0.5)  # a normal stop keeps the trajectory's scaled limits
    np.testing.assert_allclose(samples[-1].velocity, 0.0, atol=1e-9)
    assert machine.state == "stopped"


def test_emergency_stop_is_shorter_than_a_normal_stop() -> None:
    durations = {}
    for emergency in (False, True):
        machine = ExecutionStateMachine(LIMITS)
        trajectory = _trajectory()
        machine.start(trajectory, "s", now_s=0.0)
        machine.tick(0.5 * trajectory.duration_s)
        machine.stop(0.5 * trajectory.duration_s, emergency=emergency)
        durations[emergency] = machine.status(0.5 * trajectory.duration_s).duration_s
    assert durations[True] < durations[False]


WATCHDOG = ExecutorConfig(joint_state_timeout_s=0.2, max_tracking_error_rad=0.05)


def test_watchdog_stops_on_stale_joint_states_then_reports_error() -> None:
    machine = ExecutionStateMachine(LIMITS)
    trajectory = _trajectory()
    machine.start(trajectory, "w", now_s=0.0)
    sample = machine.tick(0.3)
    assert machine.check_watchdog(0.3, sample.position, 0.1, WATCHDOG) is None
    assert machine.check_watchdog(0.3, sample.position, 0.25, WATCHDOG) == ErrorCode.JOINT_STATE_STALE
    assert machine.state == "stopping" and machine.error_code == ErrorCode.JOINT_STATE_STALE
    assert "0.250 s old" in machine.error_message
    after = machine.tick(0.3)
    _assert_continuous(sample, after)
    assert machine.check_watchdog(0.31, None, 9.0, WATCHDOG) is None  # already stopping: no second fault
    _run(machine, 0.301, 5.0)
    status = machine.status(5.0)
    assert (status.state, status.last_result, status.error_code) == ("error", "aborted", ErrorCode.JOINT_STATE_STALE)
    machine.start(trajectory, "w2", now_s=6.0)  # a new execute clears the error
    assert machine.state == "executing" and machine.error_code is None


def test_watchdog_stops_on_tracking_error() -> None:
    machine = ExecutionStateMachine(LIMITS)
    machine.start(_trajectory(), "w", now_s=0.0)
    sample = machine.tick(0.2)
    measured = sample.position.copy()
    measured[3] += 0.06
    assert machine.check_watchdog(0.2, measured, 0.0, WATCHDOG) == ErrorCode.TRACKING_ERROR
    assert "joint 3" in machine.error_message
    assert machine.check_watchdog(0.2, None, float("inf"), WATCHDOG) is None


def test_an_old_joint_state_is_tracked_against_the_setpoints_of_its_time() -> None:
    """A joint state held up for longer than the latency window (a stalled driver or bus, but
    not yet stale) shows the arm where the setpoints had it then: no tracking error."""
    machine = ExecutionStateMachine(LIMITS)
    trajectory = _trajectory()
    machine.start(trajectory, "w", now_s=0.0)
    then = None
    for t in np.arange(0.0, 0.8, 0.005):
        sample = machine.tick(float(t))
        then = sample if then is None and t >= 0.35 else then
    assert then is not None
    now = machine.tick(0.8)
    assert np.abs(now.position - then.position).max() > WATCHDOG.max_tracking_error_rad
    # Arrived 0.15 s ago (stale at 0.2 s): with the window of 0.3 s before its arrival, it fits.
    assert machine.check_watchdog(0.8, then.position, 0.15, WATCHDOG) is None
    # The same position, just arrived, is far behind every setpoint of the last 0.3 s.
    assert machine.check_watchdog(0.8, then.position, 0.0, WATCHDOG) == ErrorCode.TRACKING_ERROR


def test_a_motion_from_rest_is_not_tracked_against_the_last_motions_setpoints() -> None:
    """After a motion, the arm turns up elsewhere (a restarted sim starts at home): the next
    execute starts where the arm is, and the previous motion's setpoints must not trip the watchdog."""
    machine = ExecutionStateMachine(LIMITS)
    trajectory = _trajectory()
    machine.start(trajectory, "first", now_s=0.0)
    _run(machine, 0.0, trajectory.duration_s + 0.01)
    assert machine.state == "idle"
    elsewhere = HOME + 0.5  # far from where the first motion ended
    from_there = time_parameterize(np.array([elsewhere, HOME]), max_velocity=LIMITS.velocity,
                                   max_acceleration=LIMITS.acceleration, max_jerk=LIMITS.jerk)
    start_s = trajectory.duration_s + 5.0
    machine.start(from_there, "second", now_s=start_s)
    # The watchdog runs before the first new setpoint is sampled, and then along the motion.
    assert machine.check_watchdog(start_s - 0.005, elsewhere, 0.0, WATCHDOG) is None
    sample = machine.tick(start_s)
    assert machine.check_watchdog(start_s, sample.position, 0.0, WATCHDOG) is None
    assert machine.state == "executing"
