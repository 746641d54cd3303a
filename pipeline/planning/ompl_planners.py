"""OMPL's sampling-based planners in a box-bounded joint space, behind one call.

Every planner only sees two callables (state validity and edge validity), so it runs unchanged
on the Panda (with `CollisionWorld.in_collision` / `motion_valid`) and on a 2-D point robot in
tests. The edge check is one Python call per tree edge (an OMPL `MotionValidator`), not one per
interpolated state, because the collision world checks a whole edge in one batched call.

Planners that stop at the first solution (`rrtconnect`, `rrt`, `prm`) get a cost threshold of
infinity; the asymptotically optimal ones (`rrtstar`, `prmstar`, `bitstar`, `aorrtc`) use the
whole time budget to shorten their path, as they do in MoveIt.
"""

from __future__ import annotations

import atexit
import functools
import gc
import math
import threading
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from ompl import base as ob
from ompl import geometric as og
from ompl import util as ou

from robonav.pipeline.planning.inputs import bounds_violation, joint_vector
from robonav.pipeline.planning.result import PlanResult, PlanStatus
from robonav.pipeline.types import FloatArray, MotionValidFn, StateValidFn

PLANNER_CLASSES: dict[str, Callable[[ob.SpaceInformation], ob.Planner]] = {
    "rrtconnect": og.RRTConnect,
    "rrt": og.RRT,
    "rrtstar": og.RRTstar,
    "prm": og.PRM,
    "prmstar": og.PRMstar,
    "bitstar": og.BITstar,
    "aorrtc": og.AORRTC,
}
"""OMPL planners by the `planner_id` a request names."""
OPTIMIZING = frozenset({"rrtstar", "prmstar", "bitstar", "aorrtc"})
"""Planners that keep improving their path until the time budget ends."""
ROADMAP = frozenset({"prm", "prmstar"})
"""Multi-query planners whose roadmap is kept between queries on an unchanged scene."""
_RANGED = frozenset({"rrtconnect", "rrt", "rrtstar"})
FOCUSED = frozenset({"rrtconnect", "rrt"})
"""Planners whose search starts in the focus box around the start and goals (`OmplSpace`)."""
FOCUS_SHARE = 0.5
"""Share of a solve's time limit spent sampling in the focus box before the whole joint space."""

_ompl_seeded = False
_live_spaces: weakref.WeakSet[OmplSpace] = weakref.WeakSet()
"""Every OmplSpace not yet collected, so the interpreter can release their OMPL objects on exit."""


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


@atexit.register
def _release_spaces() -> None:
    """Free the OMPL objects of every space before the bindings are torn down (see `OmplSpace.release`)."""
    for space in list(_live_spaces):
        space.release()
    gc.collect()


@dataclass(frozen=True)
class JointSpaceProblem:
    """A query for an OMPL planner: bounds, callables, start and a goal set.

    Attributes:
        lower_rad: (n,) lower joint bounds [rad].
        upper_rad: (n,) upper joint bounds [rad], each > the lower bound.
        is_valid: State validity, called with an (n,) array.
        motion_valid: Validity of the straight segment between two (n,) states, both ends
            included; OMPL calls it once per tree edge.
    """

    lower_rad: FloatArray
    upper_rad: FloatArray
    is_valid: StateValidFn
    motion_valid: MotionValidFn


class _EdgeValidator(ob.MotionValidator):
    """Checks a whole tree edge with one Python call instead of OMPL's per-state discretisation.

    It holds its space weakly, as the state validity callback does (see `OmplSpace.__init__`)."""

    def __init__(self, info: ob.SpaceInformation, space: weakref.ref[OmplSpace]) -> None:
        super().__init__(info)
        self._space = space

    def checkMotion(self, a: ob.State, b: ob.State) -> bool:  # noqa: N802 (OMPL's name)
        space = self._space()
        return space is not None and bool(space.problem.motion_valid(space.to_array(a), space.to_array(b)))


def _state_valid(space_ref: weakref.ref[OmplSpace], state: ob.State) -> bool:
    space = space_ref()
    return space is not None and bool(space.problem.is_valid(space.to_array(state)))


@dataclass(frozen=True)
class _Unsolved:
    """The last query an `OmplSpace` found no path for, with the planner that grew its trees."""

    planner_id: str
    start_rad: FloatArray
    goals_rad: FloatArray
    planner: ob.Planner
    definition: ob.ProblemDefinition

    def same_query(self, planner_id: str, start_rad: FloatArray, goals_rad: FloatArray) -> bool:
        return (planner_id == self.planner_id and np.array_equal(start_rad, self.start_rad)
                and np.array_equal(goals_rad, self.goals_rad))


class OmplSpace:
    """An OMPL state space with validity callbacks, and planners kept for reuse.

    Roadmap planners (PRM, PRM*) built here keep their roadmap between queries until
    `forget_planners` is called, which the owner does whenever the collision world changes.
    Not thread-safe for concurrent queries of the same planner.

    With `focus_margin_of_range` > 0, RRT-Connect and RRT first draw their samples from the
    focus box: the box around the start and goals grown in every joint by that share of the
    joint's range, within the bounds; after `FOCUS_SHARE` of the time limit without a solution
    they go on from the same trees in the whole space, so nothing the bounds allow is out of
    reach. Most queries (a pick, a place) need no joint far outside the range its start and
    goal span, and samples there grew trees toward postures no path needs: on MotionBenchMaker,
    1 s, a quarter of the range planned the UR5's and the Panda's problems a sixth faster
    (median), with paths a seventh and a fiftieth shorter, and on maps of the Panda's a fifth
    faster.
    """

    def __init__(self, problem: JointSpaceProblem, *, range_rad: float = 0.0, focus_margin_of_range: float = 0.0) -> None:
        lower = joint_vector(problem.lower_rad, "lower_rad")
        n = lower.shape[0]
        upper = joint_vector(problem.upper_rad, "upper_rad", n)
        for i in range(n):
            if not lower[i] < upper[i]:
                raise ValueError(f"lower_rad[{i}] = {lower[i]} must be < upper_rad[{i}] = {upper[i]}")
        if not (math.isfinite(range_rad) and range_rad >= 0):
            raise ValueError(f"range_rad must be finite and >= 0, got {range_rad}")
        if not focus_margin_of_range >= 0:  # NaN fails too; inf focuses on nothing
            raise ValueError(f"focus_margin_of_range must be >= 0, got {focus_margin_of_range}")
        ou.setLogLevel(ou.LogLevel.LOG_WARN)  # OMPL logs every solve at INFO level otherwise
        self.dof = n
        self._indices = range(n)
        self.lower_rad, self.upper_rad = lower, upper
        self.problem = problem
        self.range_rad = float(range_rad)
        self.focus_margin_of_range = float(focus_margin_of_range)
        self.space = ob.RealVectorStateSpace(n)
        self._set_bounds(lower, upper)
        self.info = ob.SpaceInformation(self.space)
        # OMPL's SpaceInformation holds both callbacks from C++, where the garbage collector cannot
        # follow them: a callback holding this space (or the validity functions, which hold their
        # owner and its collision world) would close a cycle that is never collected, one planner
        # and world lost per space (`robonav bench plan --scene camera` grew by 40-80 MB a problem
        # until the kernel killed it at 24 GB). They hold the space weakly instead.
        space = weakref.ref(self)
        self.info.setStateValidityChecker(functools.partial(_state_valid, space))
        # OMPL holds a raw reference to the validator: it must live as long as this object.
        self._validator = _EdgeValidator(self.info, space)
        self.info.setMotionValidator(self._validator)
        self.info.setup()
        self._planners: dict[str, ob.Planner] = {}
        self._unsolved: _Unsolved | None = None
        self._lock = threading.Lock()
        _live_spaces.add(self)

    def release(self) -> None:
        """Drop this space's OMPL objects; it cannot plan afterwards.

        The edge validator is a Python object that OMPL's SpaceInformation holds from C++,
        while the validator holds the SpaceInformation: a cycle the garbage collector frees
        only once nothing else refers to either. An interpreter exiting with a live space
        tears the bindings down first, and nanobind reports every object of the cycle (and
        every type and function they keep) as leaked.
        """
        with self._lock:
            self._planners.clear()
            self._unsolved = None
        self._validator = None  # type: ignore[assignment]
        self.info = None  # type: ignore[assignment]
        self.space = None  # type: ignore[assignment]

    def _set_bounds(self, lower: FloatArray, upper: FloatArray) -> None:
        # OMPL's uniform sampler reads the space's bounds at every sample: narrowing them
        # between two `solve` calls of one planner changes where its trees grow next.
        bounds = ob.RealVectorBounds(self.dof)
        for i in range(self.dof):
            bounds.setLow(i, float(lower[i]))
            bounds.setHigh(i, float(upper[i]))
        self.space.setBounds(bounds)

    def focus_box(self, start_rad: FloatArray, goals_rad: FloatArray) -> tuple[FloatArray, FloatArray] | None:
        """(lower, upper) of the box the focused search samples first, or None when it would
        be the whole space (no margin, or the start and goals span all of it)."""
        if self.focus_margin_of_range <= 0:
            return None
        ends = np.vstack([start_rad, goals_rad])
        margin = self.focus_margin_of_range * (self.upper_rad - self.lower_rad)
        lower = np.maximum(ends.min(axis=0) - margin, self.lower_rad)
        upper = np.minimum(ends.max(axis=0) + margin, self.upper_rad)
        if np.array_equal(lower, self.lower_rad) and np.array_equal(upper, self.upper_rad):
            return None
        return lower, upper

    def to_array(self, state: ob.State) -> FloatArray:
        # Called twice per edge check: an iterator into fromiter costs less than a list.
        return np.fromiter(map(state.__getitem__, self._indices), np.float64, self.dof)

    def _state(self, q: FloatArray) -> ob.State:
        state = self.space.allocState()
        for i in range(self.dof):
            state[i] = float(q[i])
        return state

    def planner(self, planner_id: str) -> ob.Planner:
        """The planner for `planner_id`; roadmap planners are created once and reused."""
        if planner_id not in PLANNER_CLASSES:
            raise ValueError(f"unknown planner_id {planner_id!r} (known: {', '.join(PLANNER_CLASSES)})")
        with self._lock:
            if planner_id in ROADMAP and planner_id in self._planners:
                planner = self._planners[planner_id]
                planner.clearQuery()
                return planner
            planner = PLANNER_CLASSES[planner_id](self.info)
            if planner_id in _RANGED and self.range_rad > 0:
                planner.setRange(self.range_rad)
            if planner_id in ROADMAP:
                self._planners[planner_id] = planner
            return planner

    def roadmap_size(self, planner_id: str) -> int:
        """Milestones in the kept roadmap of `planner_id` (0 when there is none)."""
        planner = self._planners.get(planner_id)
        return int(planner.milestoneCount()) if planner is not None else 0

    def forget_planners(self) -> None:
        """Drop kept roadmaps and the trees of the last unsolved query: their edges were checked
        against a world that has changed."""
        with self._lock:
            self._planners.clear()
            self._unsolved = None

    def solve(
        self,
        planner_id: str,
        start_rad: FloatArray,
        goals_rad: FloatArray,
        *,
        time_limit_s: float,
        stop: Callable[[], bool] | None = None,
        resume: bool = False,
    ) -> PlanResult:
        """Search from `start_rad` to any of `goals_rad` with one OMPL planner.

        Start and goals must already be valid and inside the bounds (the caller checks them
        with better error messages). Only an exact solution is a SUCCESS.

        Args:
            planner_id: A key of `PLANNER_CLASSES`.
            start_rad: (n,) start [rad].
            goals_rad: (G, n) goal set [rad], G >= 1; the path ends exactly at one of them.
            time_limit_s: Budget [s], > 0.
            stop: Polled by the planner; when it returns True the search ends early.
            resume: When the last query of this space was the same one (planner, start, goals)
                and found nothing, its planner goes on from the trees or roadmap it grew
                (OMPL planners continue where a `solve` ended). Sound only when the validity
                callbacks now accept every state and edge they accepted then (a search that
                relaxes its checks: sphere-first, then exact).

        Returns:
            A `PlanResult` whose path is (K, n), unsimplified, or TIMEOUT.
        """
        t0 = time.perf_counter()
        start = joint_vector(start_rad, "start_rad", self.dof)
        goals = np.asarray(goals_rad, dtype=np.float64)
        if goals.ndim != 2 or goals.shape[0] == 0 or goals.shape[1] != self.dof:
            raise ValueError(f"goals_rad must have shape (G >= 1, {self.dof}), got {goals.shape}")
        if not (math.isfinite(time_limit_s) and time_limit_s > 0):
            raise ValueError(f"time_limit_s must be finite and > 0, got {time_limit_s}")
        unsolved, self._unsolved = self._unsolved, None
        resumed = resume and unsolved is not None and unsolved.same_query(planner_id, start, goals)
        if resumed:
            assert unsolved is not None
            planner, definition = unsolved.planner, unsolved.definition
            definition.clearSolutionPaths()  # the approximate one it ended with
        else:
            planner = self.planner(planner_id)
            definition = ob.ProblemDefinition(self.info)
            definition.addStartState(self._state(start))
            goal_states = ob.GoalStates(self.info)
            for g in goals:
                goal_states.addState(self._state(g))
            definition.setGoal(goal_states)
            objective = ob.PathLengthOptimizationObjective(self.info)
            if planner_id not in OPTIMIZING:
                objective.setCostThreshold(ob.Cost(math.inf))  # the first solution satisfies it
            definition.setOptimizationObjective(objective)
            planner.setProblemDefinition(definition)
            planner.setup()
        focus = None if resumed or planner_id not in FOCUSED else self.focus_box(start, goals)
        if focus is None:
            status = self._run(planner, time_limit_s, stop)
        else:
            self._set_bounds(*focus)
            try:
                status = self._run(planner, FOCUS_SHARE * time_limit_s, stop)
            finally:
                self._set_bounds(self.lower_rad, self.upper_rad)
            remaining_s = time_limit_s - (time.perf_counter() - t0)
            if not self._solved(status, definition) and remaining_s > 0 and not (stop is not None and stop()):
                definition.clearSolutionPaths()  # the approximate one it ended with
                status = self._run(planner, remaining_s, stop)
        elapsed = time.perf_counter() - t0
        if not self._solved(status, definition):
            self._unsolved = _Unsolved(planner_id, start, goals, planner, definition)
            return PlanResult(PlanStatus.TIMEOUT, None,
                              f"{planner_id}: no exact solution within {time_limit_s:.3f} s (OMPL: {status})", elapsed)
        solution = definition.getSolutionPath()
        path = np.array([self.to_array(solution.getState(k)) for k in range(solution.getStateCount())])
        # OMPL copies the states; pin the ends to the exact inputs.
        path[0] = start
        path[-1] = goals[int(np.argmin(np.max(np.abs(goals - path[-1]), axis=1)))]
        return PlanResult(PlanStatus.SUCCESS, path, f"{planner_id}: {path.shape[0]} waypoints", elapsed)

    @staticmethod
    def _run(planner: ob.Planner, time_limit_s: float, stop: Callable[[], bool] | None) -> ob.PlannerStatus:
        timed = ob.timedPlannerTerminationCondition(float(time_limit_s))
        if stop is None:
            return planner.solve(timed)
        return planner.solve(ob.plannerOrTerminationCondition(timed, ob.PlannerTerminationCondition(stop)))

    @staticmethod
    def _solved(status: ob.PlannerStatus, definition: ob.ProblemDefinition) -> bool:
        return status.getStatus() == ob.PlannerStatus.EXACT_SOLUTION and definition.hasExactSolution()


def plan_ompl(
    planner_id: str,
    q_start: FloatArray,
    q_goals: FloatArray,
    *,
    lower_rad: FloatArray,
    upper_rad: FloatArray,
    is_valid: StateValidFn,
    motion_valid: MotionValidFn,
    time_limit_s: float,
    range_rad: float = 0.0,
) -> PlanResult:
    """Plan a joint-space path from `q_start` to `q_goals` with one OMPL planner, in one call.

    Bounds and start/goal validity are checked first (no OMPL call then); invalid goals are
    dropped from the set, and only when all are invalid is it GOAL_INVALID. A straight segment
    to a goal that passes `motion_valid` is returned directly. For repeated queries on one
    world, keep an `OmplSpace` instead (roadmaps are reused).

    Args:
        planner_id: A key of `PLANNER_CLASSES`.
        q_start: (n,) start configuration [rad].
        q_goals: (n,) goal or (G, n) goal set [rad].
        lower_rad: (n,) lower joint bounds [rad].
        upper_rad: (n,) upper joint bounds [rad], each > the lower bound.
        is_valid: State validity, called with an (n,) array.
        motion_valid: Validity of the straight segment between two (n,) states.
        time_limit_s: Budget for the OMPL search [s].
        range_rad: Longest tree extension (Euclidean, joint space) [rad]; 0 lets OMPL choose.

    Returns:
        A `PlanResult`; on SUCCESS its path is (K, n), K >= 2, from `q_start` to a goal.

    Raises:
        ValueError: wrong shapes, non-finite values, empty bounds, an unknown planner or a
            non-positive budget.
    """
    t0 = time.perf_counter()
    if planner_id not in PLANNER_CLASSES:
        raise ValueError(f"unknown planner_id {planner_id!r} (known: {', '.join(PLANNER_CLASSES)})")
    lower = joint_vector(lower_rad, "lower_rad")
    n = lower.shape[0]
    upper = joint_vector(upper_rad, "upper_rad", n)
    start = joint_vector(q_start, "q_start", n)
    goals = np.asarray(q_goals, dtype=np.float64)
    goals = goals[None, :] if goals.ndim == 1 else goals
    if goals.ndim != 2 or goals.shape[0] == 0:
        raise ValueError(f"q_goals must have shape ({n},) or (G >= 1, {n}), got {np.shape(q_goals)}")
    for k, goal in enumerate(goals):
        joint_vector(goal, "q_goal" if len(goals) == 1 else f"q_goals[{k}]", n)
    for i in range(n):
        if not lower[i] < upper[i]:
            raise ValueError(f"lower_rad[{i}] = {lower[i]} must be < upper_rad[{i}] = {upper[i]}")
    if not (math.isfinite(time_limit_s) and time_limit_s > 0):
        raise ValueError(f"time_limit_s must be finite and > 0, got {time_limit_s}")

    def done(status: PlanStatus, detail: str, path: FloatArray | None = None) -> PlanResult:
        return PlanResult(status, path, detail, time.perf_counter() - t0)

    problem = bounds_violation(start, lower, upper)
    if problem:
        return done(PlanStatus.OUT_OF_BOUNDS, f"start: {problem}")
    problems = [bounds_violation(g, lower, upper) for g in goals]
    if all(problems):
        return done(PlanStatus.OUT_OF_BOUNDS, f"goal: {problems[0]}")
    goals = goals[[not p for p in problems]]
    if not is_valid(start):
        return done(PlanStatus.START_INVALID, "start state is invalid (e.g. in collision)")
    goals = goals[[bool(is_valid(g)) for g in goals]]
    if goals.shape[0] == 0:
        return done(PlanStatus.GOAL_INVALID, "goal state is invalid (e.g. in collision)")
    for goal in goals:
        if motion_valid(start, goal):
            return done(PlanStatus.SUCCESS, "direct segment from start to goal is valid", np.vstack([start, goal]))
    space = OmplSpace(JointSpaceProblem(lower, upper, is_valid, motion_valid), range_rad=range_rad)
    result = space.solve(planner_id, start, goals, time_limit_s=max(time_limit_s - (time.perf_counter() - t0), 1e-3))
    return done(result.status, result.detail, result.path)
