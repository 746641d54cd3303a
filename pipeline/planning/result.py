"""Outcome of a planning call: a status, the path when there is one, and a human-readable detail."""

from __future__ import annotations

import enum
from dataclasses import dataclass

from robonav.pipeline.types import FloatArray


class PlanStatus(enum.Enum):
    """Expected planning outcomes; bad input raises ValueError instead."""

    SUCCESS = "success"
    START_INVALID = "start_invalid"
    """The start state fails the validity check (e.g. in collision)."""
    GOAL_INVALID = "goal_invalid"
    """Every goal fails the validity check (in collision, outside the workspace bounds)."""
    GOAL_UNREACHABLE = "goal_unreachable"
    """A pose goal that inverse kinematics could not reach within its tolerances."""
    OUT_OF_BOUNDS = "out_of_bounds"
    """Start or goal lies outside the joint bounds."""
    TIMEOUT = "timeout"
    """No exact solution within the time budget (an approximate one counts as none)."""


@dataclass(frozen=True, eq=False)
class PlanResult:
    """Result of one planner call.

    Attributes:
        status: What happened.
        path: (K, n) joint-space waypoints from start to goal (K >= 2) on SUCCESS, else None [rad].
        detail: Human-readable explanation (which joint is out of bounds, planner status, ...).
        planning_time_s: Wall-clock time spent in the call, including validity checks [s].
    """

    status: PlanStatus
    path: FloatArray | None
    detail: str
    planning_time_s: float

    @property
    def success(self) -> bool:
        return self.status is PlanStatus.SUCCESS
