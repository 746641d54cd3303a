"""What one planning query asks (`PlanProblem`, `PoseGoal`) and what it answers (`PlanOutcome`).

`MotionPlanner` (`motion_planner.py`) takes a `PlanProblem` and returns a `PlanOutcome`; both
are plain frozen data, so the service and the benchmarks build and read them without the planner.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

from robonav.pipeline.planning.result import PlanStatus
from robonav.pipeline.types import FloatArray


@dataclass(frozen=True)
class PoseGoal:
    """A Cartesian goal for one link, solved by IK into a goal set.

    Attributes:
        link: Link whose frame must reach the target.
        world_from_target: (4, 4) target pose of the link frame in the world frame.
        position_tolerance_m: Largest position error [m].
        orientation_tolerance_rad: Largest rotation angle error [rad]; None = position only.
    """

    link: str
    world_from_target: FloatArray
    position_tolerance_m: float = 1e-3
    orientation_tolerance_rad: float | None = 0.01


@dataclass(frozen=True)
class PlanProblem:
    """One plan query. Exactly one of `goals_rad` and `pose_goal` is given."""

    start_rad: FloatArray
    """(n,) start configuration in the robot's joint order [rad]."""
    goals_rad: FloatArray | None = None
    """(n,) goal or (G, n) goal set [rad]; the path ends at whichever goal it reaches."""
    pose_goal: PoseGoal | None = None
    planner_id: str = "rrtconnect"
    allowed_planning_time_s: float = 2.0
    num_planning_attempts: int = 1
    """Attempts within the time budget; the shortest path wins (MoveIt's parameter)."""
    seed: int = 0
    """Seeds IK restarts, goal sampling, shortcutting and `auto`'s probes. OMPL's own sampler
    is seeded once per process (see `seed_ompl_once`)."""
    simplify: bool = True
    goal_tolerance_rad: float = 0.0
    """A joint goal that is in collision or out of limits may be replaced by valid states
    within this distance in every joint [rad] (MoveIt's joint constraint tolerance)."""
    workspace_min_m: FloatArray | None = None
    """(3,) lower corner of a world-frame box the end-effector link must stay in [m]."""
    workspace_max_m: FloatArray | None = None
    """(3,) upper corner of that box [m]."""
    stop: Callable[[], bool] | None = field(default=None, compare=False)
    """Polled while searching (by OMPL's termination condition): True ends the plan early, with
    what it has (the path an optimizing planner found so far, else NO_SOLUTION). A service
    cancels long plans with it when it stops. Not used by `auto`'s forked race or the baselines."""


SearchMode = Literal["", "sphere_first", "exact", "surface"]


@dataclass(frozen=True)
class StartEscape:
    """How a plan left a start inside the robot's padding (see `start_escape`)."""

    from_rad: FloatArray
    """(n,) the requested start [rad]."""
    to_rad: FloatArray
    """(n,) the free state the search started from [rad]."""
    pairs: tuple[str, ...]
    """The `link|obstacle` pairs in contact at the requested start."""


@dataclass(frozen=True)
class PlanOutcome:
    status: PlanStatus
    detail: str
    path: FloatArray | None = None
    """(K, n) waypoints [rad] when status is SUCCESS."""
    details: dict[str, Any] = field(default_factory=dict)
    """Machine-readable specifics of a failure (colliding pairs, violated joints), as an error
    reply's `details` carries them."""
    search: SearchMode = ""
    """Which search found the path: sphere-first, exact, or against a map's surface with its
    clearance released ("surface", see `PlannerConfig.release_map_clearance`); "" before any ran."""
    start_escape: StartEscape | None = None
    """Set when the start was inside the padding and the path begins with a way out of it."""
    attempt_lengths_rad: tuple[float, ...] = ()
    """Path length of every successful attempt of `num_planning_attempts` [rad]."""
    planner_id: str = ""
    """The planner that produced the path (for `auto`, the one it chose or that won the race)."""
    planning_time_s: float = 0.0
    simplification_time_s: float = 0.0
    path_length_rad: float = 0.0
    max_joint_step_rad: float = 0.0
    min_clearance_m: float = float("inf")
    goal_index: int = 0
    """Which goal of the goal set the path ends at."""
