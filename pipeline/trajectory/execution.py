"""The executor's state machine: which trajectory is streaming, stopping it, reporting progress.

Pure and clock-agnostic: the caller passes `now_s` (any monotonic clock) to every call, so
tests drive it with a simulated clock and the service with `time.monotonic()`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from robonav.pipeline.trajectory.stopping import stop_trajectory
from robonav.pipeline.transforms import FloatArray


class SampledTrajectory(Protocol):
    @property
    def duration_s(self) -> float: ...

    def sample(self, t_s: float) -> tuple[FloatArray, FloatArray, FloatArray]: ...


@dataclass(frozen=True)
class Limits:
    velocity: FloatArray
    """(n,) [rad/s]"""
    acceleration: FloatArray
    """(n,) [rad/s^2]"""
    jerk: FloatArray
    """(n,) [rad/s^3]"""


@dataclass(frozen=True)
class SetpointSample:
    trajectory_id: str
    position: FloatArray
    velocity: FloatArray
    acceleration: FloatArray


@dataclass(frozen=True)
class ExecutionStatus:
    state: str
    trajectory_id: str
    progress: float
    time_from_start_s: float
    duration_s: float
    last_result: str
    error_code: str
    error_message: str


class ExecutionStateMachine:
    """idle → executing → (idle with last_result=succeeded) | stopping → stopped."""

    def __init__(self, limits: Limits) -> None:
        self.limits = limits
        self.state = "idle"
        self.trajectory_id = ""
        self.last_result = "none"
        self.error_code = ""
        self.error_message = ""
        self._trajectory: SampledTrajectory | None = None
        self._started_at_s = 0.0
        self._stop_scaling = 1.0
        self._last: SetpointSample | None = None

    @property
    def busy(self) -> bool:
        return self.state in ("executing", "stopping")

    def start(self, trajectory: SampledTrajectory, trajectory_id: str, now_s: float) -> None:
        if self.busy:
            raise RuntimeError(f"cannot start '{trajectory_id}': '{self.trajectory_id}' is {self.state}")
        self._trajectory = trajectory
        self._started_at_s = now_s
        self.trajectory_id = trajectory_id
        self.state = "executing"
        self.error_code = ""
        self.error_message = ""

    def stop(self, now_s: float, *, emergency: bool = False, scaling: float = 0.5) -> None:
        """Bring the arm to rest from the current setpoint within the jerk limits.

        A normal stop uses the limits scaled by `scaling`; an emergency stop uses the full limits.
        """
        if not self.busy or self._trajectory is None:
            return
        q, qd, qdd = self._trajectory.sample(now_s - self._started_at_s)
        factor = 1.0 if emergency else scaling
        self._trajectory = stop_trajectory(
            q, qd, qdd,
            max_velocity=self.limits.velocity,
            max_acceleration=self.limits.acceleration * factor,
            max_jerk=self.limits.jerk * factor,
        )
        self._started_at_s = now_s
        self.state = "stopping"

    def tick(self, now_s: float) -> SetpointSample | None:
        """The setpoint at `now_s`, or None when nothing is streaming."""
        if not self.busy or self._trajectory is None:
            return None
        t = now_s - self._started_at_s
        q, qd, qdd = self._trajectory.sample(t)
        sample = SetpointSample(self.trajectory_id, q, qd, qdd)
        self._last = sample
        if t >= self._trajectory.duration_s:
            # The final sample is exactly at rest at the goal; publish it, then go idle.
            self.last_result = "succeeded" if self.state == "executing" else "stopped"
            self.state = "idle" if self.state == "executing" else "stopped"
            self._trajectory = None
        return sample

    def status(self, now_s: float) -> ExecutionStatus:
        duration = self._trajectory.duration_s if self._trajectory is not None else 0.0
        elapsed = float(np.clip(now_s - self._started_at_s, 0.0, duration)) if self._trajectory is not None else 0.0
        progress = 1.0 if self._trajectory is None and self.last_result == "succeeded" else (
            elapsed / duration if duration > 0 else 0.0)
        return ExecutionStatus(self.state, self.trajectory_id, progress, elapsed, duration,
                               self.last_result, self.error_code, self.error_message)
