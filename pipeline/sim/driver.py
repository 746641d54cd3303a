"""What the robot side does with setpoints: follow only what the arm can do, brake when they stop.

A real arm's controller guards itself against its commanders. Franka's FCI rejects a command
whose position, velocity or acceleration jump exceeds what one 1 ms cycle allows and stops
with a reflex; its communication watchdog stops the arm when commands stop arriving; a UR's RTDE
watchdog does the same. The simulated arm applies the same two rules (`docs/protocol.md`, "What
a driver must do"):

* **Acceptance.** A setpoint is followed only if it lies within the joint limits, its velocity
  and acceleration within the arm's limits, and it continues the last followed one: over the
  time dt between them its position is within reach of the last one moving at its velocity
  (0.5 a_max dt^2, plus v_max times a small timing slack for clock jitter), its velocity within
  a_max (dt + slack). dt is the stamp difference, but never more than the time the driver
  itself saw pass since the last one was taken (plus the slack), credited with how late that
  one arrived compared with the motion's most punctual setpoint (at most `timeout_s`): a late
  setpoint followed by an on-time one is the network's delay, not a jump, yet no stamp runs
  ahead of the driver's own clock as the motion's most punctual setpoint set it, so a forged
  future stamp buys no reach. Setpoints count in
  the order they arrive: one stamped no later than the last followed one (a commander whose
  clock went back, a restarted executor) is judged by the driver's own elapsed time alone, so a
  stamp far in the future can never hold later setpoints back. While the arm rests or brakes, a
  setpoint must be one a motion starting at the driver's own command could reach since the
  driver last looked for setpoints (plus the slack): a driver that stalled for a while sees its
  commander's first setpoint that far into the motion.
* **Braking.** A rejected setpoint, or no setpoint for `timeout_s` while the commanded motion
  is moving, makes the driver brake from its own command to rest as fast as the arm's full
  limits allow (jerk-limited, each joint on its own, as the executor's emergency stop), and
  then hold. It follows setpoints again once one starts where it holds (or brakes).

Pure: the caller passes its clock (`now_s`, the sim's time) and the state its motors are
commanded to now; the counters say what happened.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np

from robonav.pipeline.trajectory.stopping import stop_trajectory
from robonav.pipeline.trajectory.trajectory import JointTrajectory
from robonav.pipeline.types import FloatArray

LIMIT_TOLERANCE_RAD = 1e-6
"""Joint limits are met within this (rounding in the commander's trajectory) [rad]."""
RATE_TOLERANCE = 1e-3
"""Velocity and acceleration limits are met within this share (the commander's rounding)."""
REJECTION_REASONS: tuple[str, ...] = ("joint_limits", "velocity", "acceleration", "jump", "bad_message")
"""Why a setpoint was not followed (`sim/stats` counts each): outside the joint limits, a
velocity or acceleration beyond the arm's, a jump from the last followed setpoint (or the
driver's own command) beyond what the limits allow in the time between, or not decodable for
this arm (wrong joints)."""


class DriverState(str, enum.Enum):
    FOLLOWING = "following"
    """Setpoints arrive and are followed."""
    BRAKING = "braking"
    """Braking to rest on its own after a rejected setpoint or a setpoint timeout."""
    HOLDING = "holding"
    """At rest where the last motion ended; waiting for a setpoint that starts there."""


@dataclass(frozen=True)
class DriverLimits:
    """The arm's own limits, (n,) each, in the joints' units."""

    lower: FloatArray
    upper: FloatArray
    velocity: FloatArray
    acceleration: FloatArray
    jerk: FloatArray


@dataclass(frozen=True)
class Rejection:
    reason: str
    """One of REJECTION_REASONS."""
    message: str


@dataclass
class DriverCounters:
    followed: int = 0
    rejected: dict[str, int] = field(default_factory=lambda: dict.fromkeys(REJECTION_REASONS, 0))
    timeouts: int = 0
    """Brakes because setpoints stopped arriving mid-motion."""
    brakes: int = 0
    """Brakes of any cause."""
    last_rejection: str = ""


class SetpointFollower:
    """Decides which setpoints the arm follows and what it commands when it follows none."""

    def __init__(self, limits: DriverLimits, q0: FloatArray, *, timeout_s: float, slack_s: float) -> None:
        """Args:
            limits: The arm's limits.
            q0: (n,) where the arm rests at the start.
            timeout_s: Setpoint watchdog: brake after this long without a followed setpoint [s].
            slack_s: Timing slack of the continuity rule [s] (see the module docstring).
        """
        if not (timeout_s > 0 and slack_s >= 0):
            raise ValueError(f"timeout_s must be > 0 and slack_s >= 0, got {timeout_s}, {slack_s}")
        self.limits = limits
        self.timeout_s = float(timeout_s)
        self.slack_s = float(slack_s)
        self.state = DriverState.HOLDING
        self.counters = DriverCounters()
        self._hold = np.array(q0, dtype=np.float64)
        self._ref: tuple[FloatArray, FloatArray, FloatArray, float, float] | None = None
        """The last followed setpoint: q, qd, qdd, its stamp, when the driver took it."""
        self._brake: JointTrajectory | None = None
        self._brake_start_s = 0.0
        self._looked_s: float | None = None
        """When the driver last looked for a setpoint (`offer` or `tick`)."""
        self._punctual_s = 0.0
        """The smallest (taken - stamp) of the motion's followed setpoints: its most punctual one."""

    def offer(self, q: FloatArray, qd: FloatArray, qdd: FloatArray, stamp_s: float, now_s: float,
              commanded: tuple[FloatArray, FloatArray]) -> Rejection | None:
        """Judge a setpoint; None means follow it. A rejection starts a brake of a moving arm.

        Args:
            q, qd, qdd: (n,) the setpoint.
            stamp_s: Its stamp [s] (the commander's clock).
            now_s: The driver's clock [s].
            commanded: (q, qd) the arm's motors are commanded to now (where a brake starts).
        """
        self._expire_rest(now_s)
        rejection = self._judge(np.asarray(q, float), np.asarray(qd, float), np.asarray(qdd, float), stamp_s, now_s)
        self._looked_s = now_s
        if rejection is None:
            offset_s = float(now_s) - float(stamp_s)
            continues = self.state is DriverState.FOLLOWING and self._ref is not None and stamp_s > self._ref[3]
            # A new motion, or a commander whose clock went back, starts its own reference.
            self._punctual_s = min(self._punctual_s, offset_s) if continues else offset_s
            self._ref = (np.array(q, float), np.array(qd, float), np.array(qdd, float), float(stamp_s), float(now_s))
            self.state = DriverState.FOLLOWING
            self._brake = None
            self.counters.followed += 1
            return None
        self.counters.rejected[rejection.reason] += 1
        self.counters.last_rejection = f"{rejection.reason}: {rejection.message}"
        if self.state is DriverState.FOLLOWING:
            self._start_brake(now_s, commanded)
        return rejection

    def reject_malformed(self, message: str, now_s: float, commanded: tuple[FloatArray, FloatArray]) -> None:
        """A setpoint that could not be read for this arm: counted, and a moving arm brakes."""
        self.counters.rejected["bad_message"] += 1
        self.counters.last_rejection = f"bad_message: {message}"
        if self.state is DriverState.FOLLOWING:
            self._start_brake(now_s, commanded)

    def tick(self, now_s: float, commanded: tuple[FloatArray, FloatArray]) -> bool:
        """Advance the watchdog and the brake; True when setpoints timed out mid-motion just now.
        Call it every time the driver looks for setpoints, whether one came or not."""
        self._looked_s = now_s
        self._expire_rest(now_s)
        if self.state is DriverState.FOLLOWING and self._ref is not None and now_s - self._ref[4] > self.timeout_s:
            self.counters.timeouts += 1
            self._start_brake(now_s, commanded)
            return True
        if self.state is DriverState.BRAKING and self._brake is not None and \
                now_s - self._brake_start_s >= self._brake.duration_s:
            self.state, self._hold, self._brake = DriverState.HOLDING, self._brake.sample(self._brake.duration_s)[0], None
        return False

    def _expire_rest(self, now_s: float) -> None:
        """A motion that ended at rest and was not continued within the timeout holds there: a
        setpoint after a pause starts from the held position, not from an old stamp's reach."""
        if self.state is DriverState.FOLLOWING and self._ref is not None and now_s - self._ref[4] > self.timeout_s:
            q, qd, qdd, _, _ = self._ref
            if not (np.any(np.abs(qd) > 1e-9) or np.any(np.abs(qdd) > 1e-9)):
                self.state, self._hold = DriverState.HOLDING, q.copy()

    def command(self, now_s: float) -> tuple[FloatArray, FloatArray] | None:
        """(q, qd) the motors must track now when the driver commands them itself (braking,
        holding), or None while it follows setpoints."""
        if self.state is DriverState.FOLLOWING:
            return None
        if self.state is DriverState.BRAKING and self._brake is not None:
            q, qd, _ = self._brake.sample(now_s - self._brake_start_s)
            return q, qd
        return self._hold.copy(), np.zeros_like(self._hold)

    def _judge(self, q: FloatArray, qd: FloatArray, qdd: FloatArray, stamp_s: float, now_s: float) -> Rejection | None:
        lim = self.limits
        outside = np.flatnonzero((q < lim.lower - LIMIT_TOLERANCE_RAD) | (q > lim.upper + LIMIT_TOLERANCE_RAD))
        if len(outside):
            j = int(outside[0])
            return Rejection("joint_limits", f"joint {j} at {q[j]:.4f} is outside [{lim.lower[j]:.4f}, {lim.upper[j]:.4f}]")
        for name, values, bound in (("velocity", qd, lim.velocity), ("acceleration", qdd, lim.acceleration)):
            over = np.flatnonzero(np.abs(values) > bound * (1 + RATE_TOLERANCE) + 1e-9)
            if len(over):
                j = int(over[0])
                return Rejection(name, f"joint {j} {name} {values[j]:.4f} exceeds its limit {bound[j]:.4f}")
        if self.state is DriverState.FOLLOWING and self._ref is not None:
            q_r, qd_r, _, stamp_r, taken_s = self._ref
            # The stamps say how much time passed, but no more than the driver saw pass itself; a
            # stamp that went back (the commander's clock did) says nothing, and the driver's does.
            seen_s = max(now_s - taken_s, 0.0) + self.slack_s
            # The last one's lateness against the motion's most punctual setpoint: bounded by the
            # watchdog, whose first-order hold allows that much anyway.
            late_s = min(max(taken_s - stamp_r - self._punctual_s, 0.0), self.timeout_s)
            dt = min(stamp_s - stamp_r, seen_s + late_s) if stamp_s > stamp_r else seen_s
            reach = 0.5 * lim.acceleration * min(dt, self.timeout_s) ** 2 + lim.velocity * self.slack_s
            position_error = np.abs(q - (q_r + qd_r * dt))
            velocity_error = np.abs(qd - qd_r)
            velocity_reach = lim.acceleration * (dt + self.slack_s)
        else:
            start_q, start_qd = self.command(now_s) or (self._hold, np.zeros_like(self._hold))
            unseen_s = self.slack_s + (0.0 if self._looked_s is None else min(max(now_s - self._looked_s, 0.0),
                                                                             self.timeout_s))
            reach = 0.5 * lim.acceleration * unseen_s ** 2 + lim.velocity * self.slack_s
            position_error = np.abs(q - (start_q + start_qd * unseen_s))
            velocity_error = np.abs(qd - start_qd)
            velocity_reach = lim.acceleration * unseen_s
        for what, error, bound in (("position", position_error, reach), ("velocity", velocity_error, velocity_reach)):
            over = np.flatnonzero(error > bound + 1e-9)
            if len(over):
                j = int(over[0])
                since = "the last followed setpoint" if self.state is DriverState.FOLLOWING else f"the arm's own command ({self.state.value})"
                return Rejection("jump", f"joint {j} {what} is {error[j]:.4f} from {since}, more than the limits "
                                         f"allow ({bound[j]:.4f})")
        return None

    def _start_brake(self, now_s: float, commanded: tuple[FloatArray, FloatArray]) -> None:
        q, qd = (np.asarray(v, dtype=np.float64) for v in commanded)
        # The commanded velocity may lag a rejected setpoint's: brake from what the motors do now.
        qd = np.clip(qd, -self.limits.velocity, self.limits.velocity)
        self._brake = stop_trajectory(q, qd, np.zeros_like(q), max_velocity=self.limits.velocity,
                                      max_acceleration=self.limits.acceleration, max_jerk=self.limits.jerk,
                                      synchronize=False)
        self._brake_start_s = now_s
        self.state = DriverState.BRAKING
        self.counters.brakes += 1
