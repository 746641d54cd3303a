"""Scripted obstacle motion: objects that slide, appear or vanish when time or the executor says so.

A `MotionScript` holds armed `ObjectMotion`s. Its owner feeds it the executor's progress
(`on_progress`) and the simulated clock (`advance`), and applies the `MotionStep`s it returns
to the world. Moving obstacles stay kinematic: they are teleported a little every physics
step, and anything in their way (the arm) is pushed or passed through, depending on how the
arm follows setpoints.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation, Slerp

from robonav.pipeline.config import require
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.wire.codes import ExecutionState

MotionAction = Literal["move", "remove", "add"]


@dataclass(frozen=True)
class ObjectMotion:
    """One scripted change of an obstacle, fired once when its trigger holds.

    Triggers: `at_s` seconds of sim time after the motion was armed, or the executor reporting
    `at_progress` of a trajectory (`trajectory_id`, or any executing one); neither fires at once.
    """

    name: str
    """The object moved, removed or added."""
    action: MotionAction = "move"
    object: SceneObject | None = None
    """add: the object, at the pose it appears at; its name must be `name`."""
    position_m: tuple[float, float, float] | None = None
    """move: target position in the world frame [m]; None keeps the position."""
    quat_xyzw: tuple[float, float, float, float] | None = None
    """move: target orientation, scalar last; None keeps the orientation."""
    duration_s: float = 0.0
    """move: time to slide to the target at constant speed (sim time) [s]; 0 jumps."""
    at_s: float | None = None
    """Trigger: sim seconds after arming [s]."""
    at_progress: float | None = None
    """Trigger: executor progress, a fraction in [0, 1]."""
    trajectory_id: str | None = None
    """With `at_progress`: only this trajectory's progress counts."""

    def __post_init__(self) -> None:
        where = f"motion of '{self.name}'"
        require(bool(self.name), "motion: name must not be empty")
        require(self.action in ("move", "remove", "add"), f"{where}: action must be move, remove or add, got {self.action!r}")
        require(self.at_s is None or self.at_progress is None, f"{where}: give at_s or at_progress, not both")
        require(self.at_s is None or (math.isfinite(self.at_s) and self.at_s >= 0), f"{where}: at_s must be >= 0, got {self.at_s}")
        require(self.at_progress is None or 0.0 <= self.at_progress <= 1.0,
                f"{where}: at_progress must be in [0, 1], got {self.at_progress}")
        require(math.isfinite(self.duration_s) and self.duration_s >= 0, f"{where}: duration_s must be >= 0, got {self.duration_s}")
        if self.action == "add":
            require(self.object is not None and self.object.name == self.name,
                    f"{where}: add needs `object` with the name '{self.name}'")
        if self.action == "move":
            require(self.position_m is not None or self.quat_xyzw is not None, f"{where}: move needs position_m or quat_xyzw")
        if self.quat_xyzw is not None:
            require(float(np.linalg.norm(self.quat_xyzw)) > 1e-9, f"{where}: quat_xyzw has zero norm")


@dataclass(frozen=True)
class MotionStep:
    """A change to apply to the world now."""

    kind: Literal["add", "pose", "remove"]
    name: str
    object: SceneObject | None = None
    """add: the object to add."""
    position_m: npt.NDArray[np.float64] | None = None
    """pose: (3,) position [m]."""
    quat_xyzw: npt.NDArray[np.float64] | None = None
    """pose: (4,) unit quaternion."""


Pose = tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]
"""(position (3,) [m], quat_xyzw (4,))."""


@dataclass
class _Armed:
    motion: ObjectMotion
    armed_at_s: float
    triggered: bool = False
    fired_at_s: float | None = None
    start: Pose | None = None
    slerp: Slerp | None = field(default=None, repr=False)


class MotionScript:
    """Armed motions and their progress; not thread-safe (one owner, the physics loop)."""

    def __init__(self) -> None:
        self._armed: list[_Armed] = []
        self.fired = 0
        """Motions triggered so far."""
        self.skipped: list[str] = []
        """Why motions were dropped (their object did not exist when they fired)."""

    @property
    def pending(self) -> int:
        """Motions armed and not finished."""
        return len(self._armed)

    def arm(self, motions: tuple[ObjectMotion, ...] | list[ObjectMotion], now_s: float) -> None:
        """Arm `motions`; `at_s` counts from `now_s` (sim time)."""
        self._armed.extend(_Armed(m, now_s) for m in motions)

    def cancel(self) -> int:
        """Drop every pending motion (a moving object stops where it is); returns how many."""
        count = len(self._armed)
        self._armed.clear()
        return count

    def on_progress(self, trajectory_id: str, state: ExecutionState, progress: float) -> None:
        """Feed one executor status; progress triggers that hold are latched."""
        if state != ExecutionState.EXECUTING:
            return
        for armed in self._armed:
            m = armed.motion
            if (m.at_progress is not None and progress >= m.at_progress
                    and (m.trajectory_id is None or m.trajectory_id == trajectory_id)):
                armed.triggered = True

    def advance(self, now_s: float, pose_of: Callable[[str], Pose | None]) -> list[MotionStep]:
        """The changes due at sim time `now_s`.

        Args:
            now_s: Current sim time [s].
            pose_of: Current pose of an object by name, None if there is no such object.

        Returns:
            Steps to apply in order; finished motions are dropped from the script.
        """
        steps: list[MotionStep] = []
        remaining: list[_Armed] = []
        for armed in self._armed:
            m = armed.motion
            if armed.fired_at_s is None:
                if m.at_s is not None:
                    armed.triggered = now_s >= armed.armed_at_s + m.at_s
                elif m.at_progress is None:
                    armed.triggered = True
                if not armed.triggered:
                    remaining.append(armed)
                    continue
                armed.fired_at_s = now_s
                self.fired += 1
                if m.action == "add":
                    steps.append(MotionStep("add", m.name, object=m.object))
                    continue
                start = pose_of(m.name)
                if start is None:
                    self.skipped.append(f"{m.action} of '{m.name}': no such object when it fired")
                    continue
                if m.action == "remove":
                    steps.append(MotionStep("remove", m.name))
                    continue
                armed.start = start
                target_quat = start[1] if m.quat_xyzw is None else np.asarray(m.quat_xyzw, float)
                armed.slerp = Slerp([0.0, 1.0], Rotation.from_quat([start[1], target_quat]))
            assert armed.start is not None and armed.slerp is not None
            fraction = 1.0 if m.duration_s == 0 else min(1.0, (now_s - armed.fired_at_s) / m.duration_s)
            target = armed.start[0] if m.position_m is None else np.asarray(m.position_m, float)
            position = armed.start[0] + fraction * (target - armed.start[0])
            steps.append(MotionStep("pose", m.name, position_m=position, quat_xyzw=armed.slerp([fraction]).as_quat()[0]))
            if fraction < 1.0:
                remaining.append(armed)
        self._armed = remaining
        return steps
