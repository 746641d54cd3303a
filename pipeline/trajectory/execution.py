"""The executor's state machine: which trajectory is streaming, preempting and stopping it, the watchdog.

Pure and clock-agnostic: the caller passes `now_s` (any monotonic clock) to every call, so
tests drive it with a simulated clock and the service with `time.monotonic()`.

States: idle → executing → idle (last_result succeeded); executing → stopping → stopped
(a stop request); executing → stopping → error (the watchdog, or a blocked path: the arm is
braked smoothly, then the machine reports `error` with `error_code` / `error_message` until the
next start); executing → stopping → replanning → executing (a blocked path with replanning on:
the arm rests while a new path is planned, then continues under the same trajectory id).
A start while executing or stopping preempts: the new trajectory is blended in from the
current commanded state, so position, velocity and acceleration stay continuous.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from robonav.pipeline.trajectory.blending import blend_from_state
from robonav.pipeline.trajectory.config import ExecutorConfig
from robonav.pipeline.trajectory.stopping import stop_trajectory
from robonav.pipeline.trajectory.trajectory import JointTrajectory, TrajectoryLimits, with_start_dwell
from robonav.pipeline.types import FloatArray
from robonav.pipeline.wire.codes import ErrorCode, ExecutionResult, ExecutionState


class SampledTrajectory(Protocol):
    @property
    def duration_s(self) -> float: ...

    def sample(self, t_s: float) -> tuple[FloatArray, FloatArray, FloatArray]: ...


Limits = TrajectoryLimits
"""(n,) velocity [rad/s], acceleration [rad/s^2] and jerk [rad/s^3] limits."""


@dataclass(frozen=True)
class SetpointSample:
    trajectory_id: str
    position: FloatArray
    velocity: FloatArray
    acceleration: FloatArray


@dataclass(frozen=True)
class ExecutionStatus:
    state: ExecutionState
    trajectory_id: str
    progress: float
    time_from_start_s: float
    duration_s: float
    last_result: ExecutionResult
    error_code: ErrorCode | None
    error_message: str
    replans: int


_RECENT_SETPOINTS = 1000
"""Setpoints kept for the tracking-error check (1 s at 1 kHz)."""


class ExecutionStateMachine:
    """Streams one trajectory at a time; see the module docstring for the states."""

    def __init__(self, limits: Limits) -> None:
        """Args: limits: the robot's full (unscaled) limits; an emergency stop uses them."""
        self.limits = limits
        self.state = ExecutionState.IDLE
        self.trajectory_id = ""
        self.last_result = ExecutionResult.NONE
        self.error_code: ErrorCode | None = None
        self.error_message = ""
        self._trajectory: SampledTrajectory | None = None
        self._started_at_s = 0.0
        self._last: SetpointSample | None = None
        self._recent_q: collections.deque[FloatArray] = collections.deque(maxlen=_RECENT_SETPOINTS)
        self._recent_t: collections.deque[float] = collections.deque(maxlen=_RECENT_SETPOINTS)
        self._fault = False
        self._replan_after_stop = False
        self.replans = 0
        """Replanned paths started under the current trajectory id."""
        self.revision = 0
        """Bumped whenever a new trajectory (a start, a blend, a stop ramp) replaces the running one."""

    @property
    def busy(self) -> bool:
        return self.state.busy

    @property
    def last_setpoint(self) -> SetpointSample | None:
        """The last sample `tick` returned (the commanded state), or None."""
        return self._last

    @property
    def trajectory(self) -> SampledTrajectory | None:
        """What streams (from `started_at_s`), or None."""
        return self._trajectory

    @property
    def started_at_s(self) -> float:
        """When `trajectory` starts, on the caller's clock [s]."""
        return self._started_at_s

    def commanded_state(self, now_s: float) -> tuple[FloatArray, FloatArray, FloatArray] | None:
        """(q, qd, qdd) the running trajectory commands at `now_s`, or None when nothing streams."""
        if not self.busy or self._trajectory is None:
            return None
        return self._trajectory.sample(now_s - self._started_at_s)

    def delay(self, delay_s: float) -> None:
        """What streams plays `delay_s` later than it was started at: the robot side started it
        late (a motion from rest that reached the setpoint loop after its start plays from its
        first row). Commanded states, stops and status follow from now on."""
        self._started_at_s += delay_s

    def start(self, trajectory: JointTrajectory, trajectory_id: str, now_s: float, *, replanned: bool = False,
              start_dwell_s: float = 0.0) -> bool:
        """Stream `trajectory` from `now_s`; while moving, blend into it from the commanded state.

        Args:
            trajectory: From `time_parameterize`; when preempting, its first segment is
                replaced by a ruckig blend from the commanded (q, qd, qdd) at `now_s` to the
                end of that segment, within the trajectory's own (scaled) limits.
            trajectory_id: Names it in setpoints and status.
            now_s: Current time on the caller's clock [s].
            replanned: A new path to the same goal after `replanning` (counted in `replans`).
            start_dwell_s: A motion from rest first stands this long at its start [s]
                (`executor.start_dwell_s`): setpoints at rest the driver takes up before the
                first moving one (see `ExecutorConfig.start_dwell_s`).

        Returns:
            True when it preempted a moving trajectory.
        """
        current = self.commanded_state(now_s)
        if current is not None:
            trajectory = blend_from_state(trajectory, *current)
        else:
            # A motion from rest is tracked against its own setpoints only: the arm may have moved
            # since the last motion ended (a restarted robot driver or simulator, hand guiding),
            # and its old setpoints would trip the watchdog before the first new one is sent.
            self._recent_q.clear()
            self._recent_t.clear()
            trajectory = with_start_dwell(trajectory, start_dwell_s)
        self._trajectory = trajectory
        self._started_at_s = now_s
        self.revision += 1
        self.trajectory_id = trajectory_id
        self.state = ExecutionState.EXECUTING
        self.error_code = None
        self.error_message = ""
        self._fault = False
        self._replan_after_stop = False
        self.replans = self.replans + 1 if replanned else 0
        return current is not None

    def stop(self, now_s: float, *, emergency: bool = False, scaling: float = 0.5, replan: bool = False) -> None:
        """Bring the arm to rest from the commanded state at `now_s`, continuous in p, v and a.

        A normal stop brakes all joints synchronised within the running trajectory's scaled
        limits (or the full limits times `scaling` when it carries none); an emergency stop
        brakes each joint as fast as its full, unscaled limits allow. With `replan` the
        machine ends in `replanning` instead of `stopped`; a stop while `replanning` ends it
        in `stopped`.
        """
        if self.state is ExecutionState.REPLANNING:
            self.state, self.last_result = ExecutionState.STOPPED, ExecutionResult.STOPPED
            return
        current = self.commanded_state(now_s)
        if current is None:
            return
        self._replan_after_stop = replan and not emergency
        running = getattr(self._trajectory, "limits", None)
        if emergency:
            limits, synchronize = self.limits, False
        elif running is not None:  # a second normal stop keeps the ramp's limits
            limits, synchronize = running, True
        else:
            limits = Limits(self.limits.velocity, self.limits.acceleration * scaling, self.limits.jerk * scaling)
            synchronize = True
        self._trajectory = stop_trajectory(
            *current,
            max_velocity=limits.velocity,
            max_acceleration=limits.acceleration,
            max_jerk=limits.jerk,
            synchronize=synchronize,
        )
        self._started_at_s = now_s
        self.revision += 1
        self.state = ExecutionState.STOPPING

    def fault(self, now_s: float, code: ErrorCode, message: str) -> None:
        """Brake smoothly (like a normal stop) and report `error` with `code` once at rest
        (at once when `replanning`, where the arm already rests)."""
        if self.state is ExecutionState.REPLANNING:
            self.state, self.last_result = ExecutionState.ERROR, ExecutionResult.ABORTED
            self.error_code, self.error_message = code, message
            return
        if not self.busy:
            return
        self.stop(now_s)
        self.error_code = code
        self.error_message = message
        self._fault = True

    def check_watchdog(self, now_s: float, measured_q: FloatArray | None, joint_state_age_s: float,
                       config: ExecutorConfig) -> ErrorCode | None:
        """Trip a fault on a stale joint state or a tracking error while executing.

        Args:
            now_s: Current time [s].
            measured_q: (n,) latest measured position in robot order [rad], or None if never received.
            joint_state_age_s: Time since that joint state arrived [s] (inf if never).
            config: The watchdog's thresholds (`joint_state_timeout_s`, `max_tracking_error_rad`,
                `tracking_latency_s`).

        Returns:
            The error code when it tripped now, else None.
        """
        if self.state is not ExecutionState.EXECUTING:
            return None  # a stop or fault is already bringing the arm to rest
        if joint_state_age_s > config.joint_state_timeout_s:
            age = "never received" if not np.isfinite(joint_state_age_s) else f"{joint_state_age_s:.3f} s old"
            self.fault(now_s, ErrorCode.JOINT_STATE_STALE,
                       f"joint state {age} (timeout {config.joint_state_timeout_s} s): stopped '{self.trajectory_id}'")
            return ErrorCode.JOINT_STATE_STALE
        if measured_q is not None and self._recent_q and \
                np.max(np.abs(self._recent_q[-1] - measured_q)) > config.max_tracking_error_rad:
            # Only then look back over the latency window (the common case costs one comparison),
            # which starts as much earlier as the measurement is old: a joint state held up (a
            # stalled driver, bus or process) shows the arm where setpoints had it then.
            since_s = now_s - joint_state_age_s - config.tracking_latency_s
            window = [q for q, t in zip(self._recent_q, self._recent_t) if t >= since_s]
            errors = np.abs(np.array(window or [self._recent_q[-1]]) - measured_q)
            error = errors[int(np.argmin(np.max(errors, axis=1)))]
            joint = int(np.argmax(error))
            if error[joint] > config.max_tracking_error_rad:
                self.fault(now_s, ErrorCode.TRACKING_ERROR,
                           f"joint {joint} is {error[joint]:.3f} rad from its setpoint (limit "
                           f"{config.max_tracking_error_rad} rad): stopped '{self.trajectory_id}'")
                return ErrorCode.TRACKING_ERROR
        return None

    def tick(self, now_s: float) -> SetpointSample | None:
        """The setpoint at `now_s`, or None when nothing is streaming."""
        if not self.busy or self._trajectory is None:
            return None
        t = now_s - self._started_at_s
        q, qd, qdd = self._trajectory.sample(t)
        sample = SetpointSample(self.trajectory_id, q, qd, qdd)
        self._last = sample
        self._recent_q.append(q)
        self._recent_t.append(now_s)
        if t >= self._trajectory.duration_s:
            # The final sample is exactly at rest at the goal; publish it, then go idle.
            if self.state is ExecutionState.EXECUTING:
                self.state, self.last_result = ExecutionState.IDLE, ExecutionResult.SUCCEEDED
            elif self._fault:
                self.state, self.last_result = ExecutionState.ERROR, ExecutionResult.ABORTED
            elif self._replan_after_stop:
                self.state = ExecutionState.REPLANNING
            else:
                self.state, self.last_result = ExecutionState.STOPPED, ExecutionResult.STOPPED
            self._trajectory = None
        return sample

    def status(self, now_s: float) -> ExecutionStatus:
        duration = self._trajectory.duration_s if self._trajectory is not None else 0.0
        elapsed = float(np.clip(now_s - self._started_at_s, 0.0, duration)) if self._trajectory is not None else 0.0
        progress = 1.0 if self._trajectory is None and self.last_result is ExecutionResult.SUCCEEDED else (
            elapsed / duration if duration > 0 else 0.0)
        return ExecutionStatus(self.state, self.trajectory_id, progress, elapsed, duration,
                               self.last_result, self.error_code, self.error_message, self.replans)
