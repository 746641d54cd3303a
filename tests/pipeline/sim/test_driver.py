"""The simulated arm's driver rules: follow only what the arm can do, brake when setpoints stop."""

from __future__ import annotations

import numpy as np
import pytest

from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.sim.driver import DriverLimits, DriverState, SetpointFollower
from robonav.pipeline.trajectory.execution import ExecutionStateMachine, Limits
from robonav.pipeline.trajectory.timing import time_parameterize
from robonav.services.config import load_config

CFG = load_config()
ROBOT = RobotModel.from_config(CFG.robot)
HOME = ROBOT.home_position_rad
LIMITS = DriverLimits(lower=ROBOT.lower_limits_rad, upper=ROBOT.upper_limits_rad, velocity=ROBOT.velocity_limits,
                      acceleration=ROBOT.acceleration_limits, jerk=ROBOT.jerk_limits)
STEP_S = 1.0 / 240.0
TRAJECTORY = time_parameterize(np.array([HOME, HOME + [1.0, 0.3, 0, 0.2, 0, 0, 0], HOME + [1.4, 0, 0.4, 0, 0, 0, 0]]),
                               max_velocity=ROBOT.velocity_limits, max_acceleration=ROBOT.acceleration_limits,
                               max_jerk=ROBOT.jerk_limits, velocity_scaling=1.0, acceleration_scaling=1.0)


def _follower() -> SetpointFollower:
    return SetpointFollower(LIMITS, HOME, timeout_s=CFG.sim.setpoint_timeout_s, slack_s=CFG.sim.setpoint_slack_s)


def _at(t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return TRAJECTORY.sample(t_s)


def _follow_until(follower: SetpointFollower, until_s: float, rng: np.random.Generator | None = None) -> float:
    """Offer the trajectory's setpoints at every physics step up to `until_s`; returns the time reached."""
    t = 0.0
    while t < until_s:
        # Stamps jitter against the driver's clock (the commander's loop and the network).
        stamp = t + (0.0 if rng is None else rng.uniform(-0.002, 0.002))
        q, qd, qdd = _at(t)
        rejection = follower.offer(q, qd, qdd, 1000.0 + stamp, t, (q, qd))
        assert rejection is None, (t, rejection)
        follower.tick(t, (q, qd))
        t += STEP_S
    return t


def test_a_trajectory_within_the_limits_is_followed_to_the_end() -> None:
    follower = _follower()
    _follow_until(follower, TRAJECTORY.duration_s + 0.05, np.random.default_rng(0))
    assert follower.state is DriverState.FOLLOWING and follower.counters.brakes == 0
    assert sum(follower.counters.rejected.values()) == 0 and follower.counters.followed > 100


@pytest.mark.parametrize(("change", "reason"), [
    (lambda q, qd, qdd: (np.where(np.arange(7) == 3, ROBOT.upper_limits_rad + 0.01, q), qd, qdd), "joint_limits"),
    (lambda q, qd, qdd: (q, qd + np.where(np.arange(7) == 1, 3.0, 0.0), qdd), "velocity"),
    (lambda q, qd, qdd: (q, qd, qdd + np.where(np.arange(7) == 0, 40.0, 0.0)), "acceleration"),
    (lambda q, qd, qdd: (q + np.where(np.arange(7) == 0, 0.2, 0.0), qd, qdd), "jump"),
    (lambda q, qd, qdd: (q, qd + np.where(np.arange(7) == 2, 1.0, 0.0), qdd), "jump"),
], ids=["beyond-joint-limit", "beyond-velocity-limit", "beyond-acceleration-limit", "position-jump", "velocity-jump"])
def test_an_impossible_setpoint_is_refused_and_the_arm_brakes_within_its_limits(change, reason: str) -> None:  # noqa: ANN001
    follower = _follower()
    t = _follow_until(follower, 0.5)
    q, qd, qdd = change(*_at(t))
    commanded = _at(t - STEP_S)[:2]
    rejection = follower.offer(q, qd, qdd, 1000.0 + t, t, commanded)
    assert rejection is not None and rejection.reason == reason, rejection
    assert follower.state is DriverState.BRAKING and follower.counters.rejected[reason] == 1
    # The brake starts where the motors were commanded, keeps every limit and ends at rest.
    states = []
    while follower.state is DriverState.BRAKING:
        follower.tick(t, commanded)
        command = follower.command(t)
        assert command is not None
        states.append(command)
        t += 0.001
    positions = np.array([s[0] for s in states])
    velocities = np.array([s[1] for s in states])
    np.testing.assert_allclose(positions[0], commanded[0], atol=1e-9)
    assert np.all(np.abs(velocities) <= LIMITS.velocity + 1e-6)
    assert np.all(np.abs(np.diff(velocities, axis=0)) <= LIMITS.acceleration * 0.001 + 1e-6)
    assert len(states) * 0.001 < 0.5 and follower.state is DriverState.HOLDING
    held, held_qd = follower.command(t)
    np.testing.assert_allclose(held_qd, 0.0)
    # The commander's trajectory goes on from where it was: refused while the arm holds elsewhere.
    later = _at(t)
    assert follower.offer(*later, 1000.0 + t, t, (held, held_qd)) is not None
    # A new motion that starts where the arm holds is followed.
    assert follower.offer(held, np.zeros(7), np.zeros(7), 1000.0 + t + 0.001, t, (held, held_qd)) is None


def test_without_setpoints_mid_motion_the_arm_brakes_to_rest_after_the_timeout() -> None:
    follower = _follower()
    t = _follow_until(follower, 0.4)
    last_t = t - STEP_S
    last_q, last_qd, _ = _at(last_t)
    assert np.abs(last_qd).max() > 0.5
    timeout_at = None
    while follower.state is not DriverState.HOLDING:
        # What the world commands meanwhile: the last setpoint held along its velocity (first order).
        commanded = (last_q + last_qd * min(t - last_t, CFG.sim.setpoint_timeout_s), last_qd)
        if follower.tick(t, commanded):
            timeout_at = t
        t += STEP_S
        assert t < 2.0, "never came to rest"
    assert timeout_at is not None and follower.counters.timeouts == 1
    assert timeout_at - 0.4 <= CFG.sim.setpoint_timeout_s + 2 * STEP_S
    assert t - 0.4 < 1.0, f"at rest {t - 0.4:.2f} s after the last setpoint"


def test_a_motion_that_ended_at_rest_just_holds() -> None:
    follower = _follower()
    q = HOME.copy()
    assert follower.offer(q, np.zeros(7), np.zeros(7), 5.0, 0.0, (q, np.zeros(7))) is None
    for t in np.arange(STEP_S, 2.0, STEP_S):  # the driver looks at every step, as the sim's does
        assert not follower.tick(float(t), (q, np.zeros(7)))
    assert follower.state is DriverState.HOLDING and follower.counters.brakes == 0
    # Long after, a setpoint far from the held position is a jump, whatever its stamp says.
    far = q + np.array([0.3, 0, 0, 0, 0, 0, 0])
    rejection = follower.offer(far, np.zeros(7), np.zeros(7), 100.0, 2.0, (q, np.zeros(7)))
    assert rejection is not None and rejection.reason == "jump"


def test_stamps_cannot_buy_reach_and_a_clock_that_went_back_holds_nothing_back() -> None:
    follower = _follower()
    t = _follow_until(follower, 0.3)
    q, qd, qdd = _at(t)
    # A stamp 10 s ahead claims time the driver never saw: only its own elapsed time counts.
    ahead = q + qd * 10.0
    rejection = follower.offer(np.clip(ahead, ROBOT.lower_limits_rad, ROBOT.upper_limits_rad), qd, qdd, 1000.0 + t + 10.0,
                               t, (q, qd))
    assert rejection is not None and rejection.reason in ("jump", "joint_limits")
    # The commander's clock went back (a restarted executor): the motion's next setpoint is still
    # followed, judged by the driver's own time; a stamp far ahead earlier holds nothing back.
    follower = _follower()
    t = _follow_until(follower, 0.3)
    assert follower.offer(*_at(t + 0.001), 5.0, t + 0.001, _at(t)[:2]) is None
    assert follower.state is DriverState.FOLLOWING and follower.counters.brakes == 0
    # A stale setpoint from far back along the motion is a jump from where the arm is: it brakes.
    rejection = follower.offer(*_at(t - 0.2), 4.0, t + 0.002, _at(t + 0.001)[:2])
    assert rejection is not None and rejection.reason == "jump"


def test_a_driver_that_stalled_takes_a_motion_from_rest_that_far_in() -> None:
    """The commander started a motion while the driver (the sim's physics loop) stalled: the
    first setpoint it sees is that far into the motion. Reach counts from its last look."""
    into = 0.08
    q, qd, qdd = _at(into)
    assert np.abs(qd).max() > 0.3
    prompt = _follower()
    prompt.tick(10.0, (HOME, np.zeros(7)))
    rejection = prompt.offer(q, qd, qdd, 1000.0 + into, 10.0 + STEP_S, (HOME, np.zeros(7)))
    assert rejection is not None and rejection.reason == "jump"  # it looked 4 ms ago: no motion gets that far
    stalled = _follower()
    stalled.tick(10.0, (HOME, np.zeros(7)))
    assert stalled.offer(q, qd, qdd, 1000.0 + into, 10.0 + into, (HOME, np.zeros(7))) is None


def test_a_late_setpoint_then_an_on_time_one_is_the_networks_delay_not_a_jump() -> None:
    follower = _follower()
    t = _follow_until(follower, 0.3)
    late_s = 0.06  # three times the slack: the router held one setpoint back
    # The setpoint stamped at t arrives late_s late; the next, stamped a step after, on time.
    assert follower.offer(*_at(t), 1000.0 + t, t + late_s, _at(t)[:2]) is None
    on_time = t + late_s + STEP_S
    assert follower.offer(*_at(on_time), 1000.0 + on_time, on_time + 0.001, _at(t)[:2]) is None
    assert follower.counters.brakes == 0
    # The credit is the delay against the motion's most punctual setpoint, no more: a stamp ahead
    # of the driver's clock as that one set it still buys no reach.
    follower = _follower()
    t = _follow_until(follower, 0.3)
    assert follower.offer(*_at(t), 1000.0 + t, t + late_s, _at(t)[:2]) is None
    ahead = t + late_s + 0.1
    rejection = follower.offer(*_at(ahead), 1000.0 + ahead, t + late_s + STEP_S, _at(t)[:2])
    assert rejection is not None and rejection.reason == "jump"


@pytest.mark.parametrize("dwell_s", [0.0, 0.1])
def test_a_motion_from_rest_with_its_dwell_is_followed_though_its_first_moving_setpoints_come_late(dwell_s: float) -> None:
    """The executor's motion from rest (`start_dwell_s`) against a router that holds back its
    first 40 ms of moving setpoints and hands them over in a bunch: without the dwell the driver,
    in hold, sees a first setpoint 40 ms into the motion and refuses it; with it, it follows the
    setpoints at rest first and then judges the bunch by stamps."""
    machine = ExecutionStateMachine(Limits(ROBOT.velocity_limits, ROBOT.acceleration_limits, ROBOT.jerk_limits))
    machine.start(TRAJECTORY, "from-rest", now_s=0.0, start_dwell_s=dwell_s)
    follower = _follower()
    held_back = (dwell_s, dwell_s + 0.04)  # setpoints stamped in here arrive at its end
    follower.tick(-STEP_S, (HOME, np.zeros(7)))
    rejections = []
    t = 0.0
    while t < dwell_s + 0.3:
        if not held_back[0] <= t < held_back[1]:
            sample = machine.tick(t)
            assert sample is not None
            rejection = follower.offer(sample.position, sample.velocity, sample.acceleration, 1000.0 + t, t,
                                       (HOME, np.zeros(7)))
            rejections.append(rejection)
        follower.tick(t, (HOME, np.zeros(7)))
        t += STEP_S
    if dwell_s == 0.0:
        assert rejections[0] is not None and rejections[0].reason == "jump"
        assert follower.counters.followed == 0  # the arm stays put: the commander's tracking watchdog stops it
    else:
        assert rejections == [None] * len(rejections) and follower.counters.brakes == 0
        assert follower.state is DriverState.FOLLOWING
