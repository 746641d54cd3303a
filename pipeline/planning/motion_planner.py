"""One planning query against a collision world: checks, OMPL search, shortcutting, metrics.

This is the planner service's core, free of Zenoh: a joint-space problem in, a path with its
metrics or a status that says why not out. Every returned path is re-validated.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from robonav.pipeline.collision import CollisionWorld
from robonav.pipeline.planning.config import PlannerConfig
from robonav.pipeline.planning.metrics import interpolate_path, max_joint_step_rad, path_length_rad
from robonav.pipeline.planning.result import PlanStatus
from robonav.pipeline.planning.rrt_connect import plan_rrt_connect
from robonav.pipeline.planning.shortcut import shortcut_path
from robonav.pipeline.robot import RobotModel
from robonav.pipeline.transforms import FloatArray

PLANNERS: tuple[str, ...] = ("rrtconnect",)
CLEARANCE_SAMPLES = 12


@dataclass(frozen=True)
class PlanProblem:
    start_rad: FloatArray
    """(n,) start configuration in the robot's joint order [rad]."""
    goal_rad: FloatArray
    """(n,) goal configuration [rad]."""
    planner_id: str = "rrtconnect"
    allowed_planning_time_s: float = 2.0
    seed: int = 0
    """Seeds the shortcutting; OMPL's own sampler is seeded per process."""
    simplify: bool = True


@dataclass(frozen=True)
class PlanOutcome:
    status: PlanStatus
    detail: str
    path: FloatArray | None = None
    """(K, n) waypoints [rad] when status is SUCCESS."""
    details: dict[str, Any] = field(default_factory=dict)
    """Machine-readable specifics: colliding pairs, violated joints."""
    planning_time_s: float = 0.0
    simplification_time_s: float = 0.0
    path_length_rad: float = 0.0
    max_joint_step_rad: float = 0.0
    min_clearance_m: float = float("inf")


class MotionPlanner:
    """Plans for one robot in one collision world (the world is updated by the caller)."""

    def __init__(self, robot: RobotModel, world: CollisionWorld, config: PlannerConfig) -> None:
        self.robot = robot
        self.world = world
        self.config = config

    def plan(self, problem: PlanProblem) -> PlanOutcome:
        if problem.planner_id not in PLANNERS:
            raise ValueError(f"unknown planner_id {problem.planner_id!r} (known: {', '.join(PLANNERS)})")
        start = self.robot.validate_q(problem.start_rad, "start")
        goal = self.robot.validate_q(problem.goal_rad, "goal")
        for label, q in (("start", start), ("goal", goal)):
            violations = self.robot.check_joint_limits(q)
            if violations:
                return PlanOutcome(PlanStatus.OUT_OF_BOUNDS, f"{label} is outside the joint limits: {'; '.join(violations)}",
                                   details={"which": label, "violations": violations})
        for label, q, status in (("start", start, PlanStatus.START_INVALID), ("goal", goal, PlanStatus.GOAL_INVALID)):
            pairs = self.world.collisions(q)
            if pairs:
                named = [f"{a}|{b}" for a, b in pairs]
                return PlanOutcome(status, f"{label} is in collision: {', '.join(named)}", details={"pairs": named})

        resolution = self.config.edge_resolution_rad

        def motion_valid(a: FloatArray, b: FloatArray) -> bool:
            return self.world.motion_valid(a, b, resolution)

        def is_valid(q: FloatArray) -> bool:
            return not self.world.in_collision(q)

        result = plan_rrt_connect(
            start, goal,
            lower_rad=self.robot.lower_limits_rad, upper_rad=self.robot.upper_limits_rad,
            is_valid=is_valid, motion_valid=motion_valid,
            time_limit_s=problem.allowed_planning_time_s, range_rad=self.config.range_rad,
        )
        if result.status is not PlanStatus.SUCCESS or result.path is None:
            return PlanOutcome(result.status, result.detail, planning_time_s=result.planning_time_s)

        path = result.path
        simplify_start = time.perf_counter()
        if problem.simplify and len(path) > 2:
            path = shortcut_path(path, motion_valid=motion_valid, rng=np.random.default_rng(problem.seed),
                                 iterations=self.config.shortcut_iterations)
        simplification_time_s = time.perf_counter() - simplify_start
        # Re-validate what we return: a path is only as good as its last check.
        if not self.world.path_valid(path, resolution):
            return PlanOutcome(PlanStatus.TIMEOUT, "the found path failed re-validation",
                               planning_time_s=result.planning_time_s)
        return PlanOutcome(
            PlanStatus.SUCCESS, "ok", path=path,
            planning_time_s=result.planning_time_s,
            simplification_time_s=simplification_time_s,
            path_length_rad=path_length_rad(path),
            max_joint_step_rad=max_joint_step_rad(path),
            min_clearance_m=self._sampled_clearance_m(path),
        )

    def _sampled_clearance_m(self, path: FloatArray) -> float:
        """Clearance at the waypoints and evenly spread states between them.

        FCL's octree distance costs ~10 ms per Panda state, so the exact minimum over a finely
        interpolated path would cost seconds; this reports the minimum over at most
        `CLEARANCE_SAMPLES` states (the path itself is collision-checked finely regardless).
        """
        dense = interpolate_path(path, self.config.edge_resolution_rad)
        if len(dense) > CLEARANCE_SAMPLES:
            dense = dense[np.linspace(0, len(dense) - 1, CLEARANCE_SAMPLES).round().astype(int)]
        return min(self.world.clearance_m(q) for q in dense)
