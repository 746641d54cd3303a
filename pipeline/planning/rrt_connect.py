"""Bidirectional RRT (OMPL's RRTConnect) in a box-bounded joint space.

The planner only sees two callables, so it runs unchanged on the Panda (with
`CollisionWorld.in_collision` / `motion_valid`) and on a 2-D point robot in tests.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np
from ompl import base as ob
from ompl import geometric as og
from ompl import util as ou

from robonav.pipeline.planning.result import PlanResult, PlanStatus
from robonav.pipeline.transforms import FloatArray

_ompl_seeded = False


def seed_ompl_once(seed: int) -> bool:
    """Seed OMPL's global RNG on the first call in this process; later calls do nothing.

    OMPL derives every sampler's seed from one process-wide seed that can only take effect
    before the first sampler exists (a later `RNG.setSeed` just logs "Changing seed now will
    not lead to deterministic sampling"), so a planner process seeds once at start-up.
    OMPL rejects seed 0 (it logs a warning and uses 1), so `seed` is passed on as `seed + 1`.

    Args:
        seed: 0 <= seed < 2**32 - 1.

    Returns:
        True when this call set the seed.
    """
    global _ompl_seeded
    if not 0 <= seed < 2**32 - 1:
        raise ValueError(f"seed must be in [0, 2**32 - 1), got {seed}")
    if _ompl_seeded:
        return False
    ou.RNG.setSeed(int(seed) + 1)
    _ompl_seeded = True
    return True


def plan_rrt_connect(
    q_start: FloatArray,
    q_goal: FloatArray,
    *,
    lower_rad: FloatArray,
    upper_rad: FloatArray,
    is_valid: Callable[[FloatArray], bool],
    motion_valid: Callable[[FloatArray, FloatArray], bool],
    time_limit_s: float,
    range_rad: float = 0.0,
) -> PlanResult:
    """Plan a joint-space path from `q_start` to `q_goal` with RRTConnect.

    Bounds and start/goal validity are checked first (no OMPL call then). A straight segment
    that passes `motion_valid` is returned directly. Only an exact OMPL solution is a SUCCESS;
    an approximate one, or none within `time_limit_s`, is TIMEOUT.

    Args:
        q_start: (n,) start configuration [rad].
        q_goal: (n,) goal configuration [rad].
        lower_rad: (n,) lower joint bounds [rad].
        upper_rad: (n,) upper joint bounds [rad], each > the lower bound.
        is_valid: State validity, called with an (n,) array.
        motion_valid: Validity of the straight segment between two (n,) states, both ends
            included; OMPL calls it once per tree edge.
        time_limit_s: Budget for the OMPL search [s].
        range_rad: Longest tree extension (Euclidean, joint space) [rad]; 0 lets OMPL choose.

    Returns:
        A `PlanResult`; on SUCCESS its path is (K, n), K >= 2, starting at `q_start` and
        ending at `q_goal`, unsimplified.

    Raises:
        ValueError: wrong shapes, non-finite values, empty bounds, or a non-positive budget.
    """
    t0 = time.perf_counter()
    lower = _vector(lower_rad, "lower_rad")
    n = lower.shape[0]
    upper = _vector(upper_rad, "upper_rad", n)
    start = _vector(q_start, "q_start", n)
    goal = _vector(q_goal, "q_goal", n)
    for i in range(n):
        if not lower[i] < upper[i]:
            raise ValueError(f"lower_rad[{i}] = {lower[i]} must be < upper_rad[{i}] = {upper[i]}")
    if not (math.isfinite(time_limit_s) and time_limit_s > 0):
        raise ValueError(f"time_limit_s must be finite and > 0, got {time_limit_s}")
    if not (math.isfinite(range_rad) and range_rad >= 0):
        raise ValueError(f"range_rad must be finite and >= 0, got {range_rad}")

    def done(status: PlanStatus, detail: str, path: FloatArray | None = None) -> PlanResult:
        return PlanResult(status, path, detail, time.perf_counter() - t0)

    for label, q in (("start", start), ("goal", goal)):
        problem = _bounds_violation(q, lower, upper)
        if problem:
            return done(PlanStatus.OUT_OF_BOUNDS, f"{label}: {problem}")
    if not is_valid(start):
        return done(PlanStatus.START_INVALID, "start state is invalid (e.g. in collision)")
    if not is_valid(goal):
        return done(PlanStatus.GOAL_INVALID, "goal state is invalid (e.g. in collision)")
    if motion_valid(start, goal):
        return done(PlanStatus.SUCCESS, "direct segment from start to goal is valid", np.vstack([start, goal]))

    ou.setLogLevel(ou.LogLevel.LOG_WARN)  # OMPL logs every solve at INFO level otherwise
    space = ob.RealVectorStateSpace(n)
    bounds = ob.RealVectorBounds(n)
    for i in range(n):
        bounds.setLow(i, float(lower[i]))
        bounds.setHigh(i, float(upper[i]))
    space.setBounds(bounds)
    setup = og.SimpleSetup(space)
    info = setup.getSpaceInformation()

    def state_array(state: ob.State) -> FloatArray:
        return np.array([state[i] for i in range(n)], dtype=np.float64)

    setup.setStateValidityChecker(lambda state: bool(is_valid(state_array(state))))
    validator = _EdgeValidator(info, lambda a, b: bool(motion_valid(state_array(a), state_array(b))))
    info.setMotionValidator(validator)  # `validator` must outlive solve(): OMPL holds a raw reference

    ompl_start, ompl_goal = space.allocState(), space.allocState()
    for i in range(n):
        ompl_start[i] = float(start[i])
        ompl_goal[i] = float(goal[i])
    setup.setStartAndGoalStates(ompl_start, ompl_goal)
    planner = og.RRTConnect(info)
    if range_rad > 0:
        planner.setRange(float(range_rad))
    setup.setPlanner(planner)

    status = setup.solve(float(time_limit_s))
    if status.getStatus() != ob.PlannerStatus.EXACT_SOLUTION or not setup.haveExactSolutionPath():
        return done(PlanStatus.TIMEOUT, f"no exact solution within {time_limit_s:.3f} s (OMPL: {status})")
    solution = setup.getSolutionPath()
    path = np.array([state_array(solution.getState(k)) for k in range(solution.getStateCount())])
    # OMPL copies the states; pin the ends to the exact inputs.
    path[0], path[-1] = start, goal
    return done(PlanStatus.SUCCESS, f"RRTConnect: {path.shape[0]} waypoints", path)


class _EdgeValidator(ob.MotionValidator):
    """Checks a whole tree edge with one Python call instead of OMPL's per-state discretisation."""

    def __init__(self, info: ob.SpaceInformation, check: Callable[[ob.State, ob.State], bool]) -> None:
        super().__init__(info)
        self._check = check

    def checkMotion(self, a: ob.State, b: ob.State) -> bool:  # noqa: N802 (OMPL's name)
        return self._check(a, b)


def _vector(value: FloatArray, label: str, n: int | None = None) -> FloatArray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != 1 or arr.shape[0] == 0 or (n is not None and arr.shape[0] != n):
        expected = f"({n},)" if n is not None else "(n >= 1,)"
        raise ValueError(f"{label} must have shape {expected}, got shape {arr.shape}")
    bad = np.flatnonzero(~np.isfinite(arr))
    if bad.size:
        raise ValueError(f"{label}[{int(bad[0])}] must be finite, got {arr[bad[0]]}")
    return arr


def _bounds_violation(q: FloatArray, lower: FloatArray, upper: FloatArray) -> str:
    for i in range(q.shape[0]):
        if q[i] < lower[i]:
            return f"joint {i} = {q[i]:.6g} is below its lower bound {lower[i]:.6g}"
        if q[i] > upper[i]:
            return f"joint {i} = {q[i]:.6g} is above its upper bound {upper[i]:.6g}"
    return ""
