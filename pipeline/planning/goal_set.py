"""Where a query may end, and why its start or a goal cannot be planned from or to.

A query's goal is joint positions (one goal or a set, optionally with a tolerance that replaces
a goal in collision by free states around it) or a Cartesian pose, turned into a set of
distinct inverse-kinematics solutions. The planner searches to whichever member it reaches
first (MoveIt's goal constraints: joint tolerances or a pose with its tolerances).
"""

from __future__ import annotations

import math

import numpy as np

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.planning.config import PlannerConfig
from robonav.pipeline.planning.ik import IkStatus, solve_ik
from robonav.pipeline.planning.problem import PlanOutcome, PlanProblem
from robonav.pipeline.planning.result import PlanStatus
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.types import FloatArray, StateValidFn

NEAR_GOAL_SAMPLES = 64
"""States drawn within a goal's tolerance when the goal itself is in collision."""
NEAR_GOALS_KEPT = 4
"""Free states near a colliding goal that join the goal set, nearest first."""


def state_problem(robot: RobotModel, world: CollisionWorld, q: FloatArray, is_valid: StateValidFn, which: str,
                  invalid: PlanStatus) -> PlanOutcome | None:
    """Why the start or a goal `q` cannot be planned from or to (limits, collisions with the
    colliding pairs named, workspace bounds), or None. `which` names it in the outcome."""
    violations = robot.check_joint_limits(q)
    if violations:
        return PlanOutcome(PlanStatus.OUT_OF_BOUNDS, f"{which} is outside the joint limits: {'; '.join(violations)}",
                           details={"which": which, "violations": violations})
    pairs = world.collisions(q)
    if pairs:
        named = [f"{a}|{b}" for a, b in pairs]
        return PlanOutcome(invalid, f"{which} is in collision: {', '.join(named)}",
                           details={"pairs": named, "which": which, "positions": q.tolist()})
    if not is_valid(q):
        return PlanOutcome(invalid, f"{which}: the end-effector is outside the workspace bounds",
                           details={"which": which, "workspace": True})
    return None


def goal_set(robot: RobotModel, world: CollisionWorld, config: PlannerConfig, problem: PlanProblem,
             start: FloatArray, is_valid: StateValidFn, rng: np.random.Generator) -> FloatArray | PlanOutcome:
    """The (G, dof) goal set of `problem`, or a PlanOutcome saying why there is none.

    Raises:
        ValueError: neither or both of a joint and a pose goal, a malformed joint goal or tolerance.
    """
    if (problem.goals_rad is None) == (problem.pose_goal is None):
        raise ValueError("give exactly one of goals_rad and pose_goal")
    if problem.pose_goal is not None:
        return _pose_goal_set(robot, world, config, problem, start, is_valid, rng)
    goals = np.asarray(problem.goals_rad, dtype=np.float64)
    goals = goals[None, :] if goals.ndim == 1 else goals
    if goals.ndim != 2 or goals.shape[0] == 0:
        raise ValueError(f"goals_rad must have shape ({robot.dof},) or (G >= 1, {robot.dof})")
    goals = np.array([robot.validate_q(g, "goal" if len(goals) == 1 else f"goals[{k}]") for k, g in enumerate(goals)])
    tolerance = problem.goal_tolerance_rad
    if not (math.isfinite(tolerance) and tolerance >= 0):
        raise ValueError(f"goal_tolerance_rad must be finite and >= 0, got {tolerance}")
    kept: list[FloatArray] = []
    first_problem: PlanOutcome | None = None
    for goal in goals:
        problem_here = state_problem(robot, world, goal, is_valid, "goal", PlanStatus.GOAL_INVALID)
        if problem_here is None:
            kept.append(goal)
            continue
        first_problem = first_problem or problem_here
        if tolerance > 0:
            kept.extend(_goals_near(robot, goal, tolerance, is_valid, rng))
    if kept:
        return np.array(kept)
    assert first_problem is not None  # every goal was refused
    return first_problem


def _goals_near(robot: RobotModel, goal: FloatArray, tolerance: float, is_valid: StateValidFn,
                rng: np.random.Generator) -> list[FloatArray]:
    """Free states within `tolerance` of `goal` in every joint, nearest first."""
    low = np.maximum(goal - tolerance, robot.lower_limits_rad)
    high = np.minimum(goal + tolerance, robot.upper_limits_rad)
    candidates = rng.uniform(low, high, size=(NEAR_GOAL_SAMPLES, goal.shape[0]))
    valid = [q for q in candidates if is_valid(q)]
    valid.sort(key=lambda q: float(np.max(np.abs(q - goal))))
    return valid[:NEAR_GOALS_KEPT]


def _pose_goal_set(robot: RobotModel, world: CollisionWorld, config: PlannerConfig, problem: PlanProblem,
                   start: FloatArray, is_valid: StateValidFn, rng: np.random.Generator) -> FloatArray | PlanOutcome:
    pose = problem.pose_goal
    assert pose is not None
    result = solve_ik(
        robot, pose.world_from_target, pose.link, rng=rng,
        position_tolerance_m=pose.position_tolerance_m, orientation_tolerance_rad=pose.orientation_tolerance_rad,
        is_valid=_goal_validity(world, config, is_valid), seed_q=start, max_restarts=config.ik_restarts,
        max_solutions=config.ik_solutions,
    )
    details = {"position_error_m": result.best_position_error_m,
               "orientation_error_rad": result.best_orientation_error_rad, "attempts": result.attempts}
    if result.status is IkStatus.UNREACHABLE:
        return PlanOutcome(PlanStatus.GOAL_UNREACHABLE, f"no IK solution for {pose.link}: {result.detail}",
                           details=details)
    if result.status is IkStatus.GOAL_IN_COLLISION:
        details |= {"rejected": result.rejected_invalid, "which": "goal"}
        if len(result.rejected):  # where the nearest rejected solution collides, for a viewer to show
            q = result.rejected[0]
            details |= {"positions": q.tolist(), "pairs": [f"{a}|{b}" for a, b in world.collisions(q)]}
        return PlanOutcome(PlanStatus.GOAL_INVALID,
                           f"every IK solution for {pose.link} is in collision: {result.detail}", details=details)
    return robot.nearest_turn_rad(result.solutions, start)


def _goal_validity(world: CollisionWorld, config: PlannerConfig, is_valid: StateValidFn) -> StateValidFn:
    """`is_valid` for an IK solution: near a surface the solution is an anchor of its own check,
    as the query's joint goals are (`MotionPlanner.plan`)."""
    if not world.has_surface_allowance:
        return is_valid

    def valid(q: FloatArray) -> bool:
        with world.anchored(np.vstack([world.anchors, q]), config.surface_allowance_rad):
            return is_valid(q)
    return valid
