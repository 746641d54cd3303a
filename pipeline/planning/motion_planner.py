"""One planning query against a collision world: its goal set (`goal_set.py`), checks, search,
simplification, metrics.

This is the planner service's core, free of Zenoh: a joint-space problem (joint goals, a goal
set or a Cartesian pose goal) in, a path with its metrics or a status that says why not out.
Every returned path is re-validated exactly against the collision world, at the path check
resolution (the edge resolution unless set finer).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections import deque
from collections.abc import Callable

import numpy as np

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.planning.baselines.lattice import plan_lattice
from robonav.pipeline.planning.baselines.potential_field import PotentialFieldConfig, plan_potential_field
from robonav.pipeline.planning.config import PlannerConfig
from robonav.pipeline.planning.goal_set import goal_set, state_problem
from robonav.pipeline.planning.metrics import interpolate_path, max_joint_step_rad, path_length_rad
from robonav.pipeline.planning.ompl_planners import PLANNER_CLASSES, JointSpaceProblem, OmplSpace
from robonav.pipeline.planning.problem import PlanOutcome as PlanOutcome
from robonav.pipeline.planning.problem import PlanProblem as PlanProblem
from robonav.pipeline.planning.problem import PoseGoal as PoseGoal
from robonav.pipeline.planning.problem import SearchMode as SearchMode
from robonav.pipeline.planning.problem import StartEscape as StartEscape
from robonav.pipeline.planning.race import race
from robonav.pipeline.planning.recheck import path_rechecked, recording
from robonav.pipeline.planning.result import PlanResult, PlanStatus
from robonav.pipeline.planning.shortcut import shortcut_path
from robonav.pipeline.planning.start_escape import escape_start
from robonav.pipeline.planning.workspace import workspace_validity
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.types import FloatArray, MotionValidFn, StateValidFn

BASELINES: tuple[str, ...] = ("astar", "dijkstra", "potential_field")
"""Seed baselines the literature compares against (slow in 7-D; see their modules)."""
PLANNERS: tuple[str, ...] = (*PLANNER_CLASSES, *BASELINES, "auto")
CLEARANCE_SAMPLES = 12
MAX_SELF_OVERFLAG = 0.75
"""Above this share of free states flagged by self-collision spheres, skip the sphere-first search
(the Panda with its finger pairs allowed: 0.3 of random states; with them checked: 1.0)."""
_AUTO_HISTORY = 20
"""Outcomes per planner that `auto` remembers for the current world."""


class MotionPlanner:
    """Plans for one robot in one collision world (the world is updated by the caller).

    OMPL planners and PRM roadmaps are kept while `world.revision` is unchanged. Not
    thread-safe: callers serialise `plan` and world updates.
    """

    def __init__(self, robot: RobotModel, world: CollisionWorld, config: PlannerConfig) -> None:
        self.robot = robot
        self.world = world
        self.config = config
        resolution = config.edge_resolution_rad
        # Sphere-first mode (see `_attempt`): anchors are the query's start and goals, where FCL
        # still decides what the spheres flag; elsewhere a flagged state counts as blocked.
        self._sphere_first = False
        self._anchors: list[FloatArray] = []
        self._is_valid = lambda q: (world.state_free_by_spheres(q, self._near_anchor) if self._sphere_first
                                    else not world.in_collision(q))
        self._motion_valid = lambda a, b: (world.motion_free_by_spheres(a, b, resolution, self._near_anchor)
                                           if self._sphere_first else world.motion_valid(a, b, resolution))
        self._space = self._new_space(self._is_valid, self._motion_valid)
        self._space_revision = world.revision
        self._history: dict[str, deque[bool]] = {}

    def _new_space(self, is_valid: StateValidFn, motion_valid: MotionValidFn) -> OmplSpace:
        return OmplSpace(JointSpaceProblem(self.robot.lower_limits_rad, self.robot.upper_limits_rad, is_valid,
                                           motion_valid),
                         range_rad=self.config.range_rad, focus_margin_of_range=self.config.focus_margin_of_range)

    def _sync_world(self) -> None:
        if self.world.revision != self._space_revision:
            self._space.forget_planners()
            self._history.clear()
            self._space_revision = self.world.revision

    def roadmap_size(self, planner_id: str = "prm") -> int:
        """Milestones in the kept roadmap of a roadmap planner (0 after a world change)."""
        self._sync_world()
        return self._space.roadmap_size(planner_id)

    def plan(self, problem: PlanProblem) -> PlanOutcome:
        """Plan `problem`; expected failures come back as a status, bad input raises ValueError.

        Against a map with a clearance, the start and the goals are anchors: near them the
        clearance is released (`CollisionWorld.anchored`, `config.surface_allowance_rad`).
        A continuous joint's goal angle is replaced by its equivalent nearest the start within
        its range (`turns.py`): the path turns the short way and ends at that angle."""
        t0 = time.perf_counter()
        problem = self._nearest_turns(problem)
        if not self.world.has_surface_allowance:
            return self._plan(problem, t0)
        # Validity near the anchors differs from query to query: no roadmap outlives one.
        self._space.forget_planners()
        anchors = [self.robot.validate_q(problem.start_rad, "start")]
        if problem.goals_rad is not None:
            goals = np.asarray(problem.goals_rad, dtype=np.float64)
            anchors += list(goals.reshape(-1, self.robot.dof)) if goals.size % self.robot.dof == 0 else []
        with self.world.anchored(np.array(anchors), self.config.surface_allowance_rad):
            return self._plan(problem, t0)

    def _nearest_turns(self, problem: PlanProblem) -> PlanProblem:
        turning = self.robot.continuous_mask
        goals = None if problem.goals_rad is None else np.asarray(problem.goals_rad, dtype=np.float64)
        if goals is None or not turning.any() or goals.ndim not in (1, 2) or goals.shape[-1] != self.robot.dof:
            return problem  # nothing wraps, or a malformed goal `goal_set` refuses by name
        start = self.robot.validate_q(problem.start_rad, "start")
        return dataclasses.replace(problem, goals_rad=self.robot.nearest_turn_rad(goals, start))

    def _plan(self, problem: PlanProblem, t0: float) -> PlanOutcome:
        if problem.planner_id not in PLANNERS:
            raise ValueError(f"unknown planner_id {problem.planner_id!r} (known: {', '.join(PLANNERS)})")
        if problem.num_planning_attempts < 1:
            raise ValueError(f"num_planning_attempts must be >= 1, got {problem.num_planning_attempts}")
        if not (math.isfinite(problem.allowed_planning_time_s) and problem.allowed_planning_time_s > 0):
            raise ValueError(f"allowed_planning_time must be finite and > 0, got {problem.allowed_planning_time_s}")
        self._sync_world()
        rng = np.random.default_rng(problem.seed)
        start = self.robot.validate_q(problem.start_rad, "start")
        is_valid, motion_valid = workspace_validity(self.robot, problem.workspace_min_m, problem.workspace_max_m,
                                                    self._is_valid, self._motion_valid, self.config.edge_resolution_rad)
        real_start: FloatArray | None = None
        start_problem = state_problem(self.robot, self.world, start, is_valid, "start", PlanStatus.START_INVALID)
        if start_problem is not None:
            escape = None if start_problem.status is not PlanStatus.START_INVALID else escape_start(
                self.world, start, is_valid, rng, radius_rad=self.config.start_escape_rad,
                samples=self.config.start_escape_samples, resolution_rad=self.config.edge_resolution_rad)
            if escape is None:
                return start_problem
            real_start, start = start, escape

        goals = goal_set(self.robot, self.world, self.config, problem, start, is_valid, rng)
        if isinstance(goals, PlanOutcome):
            return goals
        if self.world.has_surface_allowance:
            # The goal set (IK solutions, goals near a colliding one) and an escaped start anchor the search.
            with self.world.anchored(np.vstack([start, goals] if real_start is None else [real_start, start, goals]),
                                     self.config.surface_allowance_rad):
                return self._search_attempts(problem, t0, start, real_start, start_problem, goals, is_valid,
                                             motion_valid, rng)
        return self._search_attempts(problem, t0, start, real_start, start_problem, goals, is_valid, motion_valid, rng)

    def _search_attempts(self, problem: PlanProblem, t0: float, start: FloatArray, real_start: FloatArray | None,
                         start_problem: PlanOutcome | None, goals: FloatArray, is_valid: StateValidFn,
                         motion_valid: MotionValidFn, rng: np.random.Generator) -> PlanOutcome:
        best: PlanOutcome | None = None
        last_failure: PlanOutcome | None = None
        lengths: list[float] = []
        deadline = t0 + problem.allowed_planning_time_s
        for _attempt in range(problem.num_planning_attempts):
            budget = deadline - time.perf_counter()
            if budget <= 0 or (problem.stop is not None and problem.stop()):
                break
            outcome = self._attempt(problem, start, goals, is_valid, motion_valid, budget, rng)
            if outcome.status is PlanStatus.SUCCESS:
                lengths.append(outcome.path_length_rad)
                if best is None or outcome.path_length_rad < best.path_length_rad:
                    best = outcome
                if outcome.path is not None and len(outcome.path) == 2:
                    break  # a straight segment cannot be beaten
            else:
                last_failure = outcome
        if best is None:
            return last_failure or PlanOutcome(PlanStatus.TIMEOUT, "no planning time left", planner_id=problem.planner_id)
        best = dataclasses.replace(best, attempt_lengths_rad=tuple(lengths))
        if real_start is None or start_problem is None:
            return best
        return self._from_real_start(best, real_start, start_problem)

    def _from_real_start(self, outcome: PlanOutcome, real_start: FloatArray, start_problem: PlanOutcome) -> PlanOutcome:
        """`outcome` planned from an escape state, with the real start put in front (see `start_escape`)."""
        assert outcome.path is not None
        path = np.vstack([real_start, outcome.path])
        escape = StartEscape(from_rad=real_start, to_rad=outcome.path[0], pairs=tuple(start_problem.details.get("pairs", ())))
        clearance = outcome.min_clearance_m
        if self.config.report_clearance:
            clearance = min(clearance, self.world.clearance_m(real_start))
        return dataclasses.replace(
            outcome, path=path, path_length_rad=path_length_rad(path), max_joint_step_rad=max_joint_step_rad(path),
            min_clearance_m=clearance, detail=f"{outcome.detail}; left the start's padding ({start_problem.detail})",
            start_escape=escape)

    def _near_anchor(self, q: FloatArray) -> bool:
        # Asked at the first suspect state of nearly every blocked edge: a loop of dot products
        # over the few anchors costs a third of one vectorised norm and min.
        radius_sq = self.config.sphere_first_exact_radius_rad ** 2
        for anchor in self._anchors:
            offset = anchor - q
            if offset.dot(offset) <= radius_sq:
                return True
        return False

    def _attempt(self, problem: PlanProblem, start: FloatArray, goals: FloatArray, is_valid: StateValidFn,
                 motion_valid: MotionValidFn,
                 budget_s: float, rng: np.random.Generator) -> PlanOutcome:
        """Search, sphere-first, then exactly if that found nothing.

        Sphere-first: a state whose covering spheres touch nothing is free (they contain the
        padded hulls, so it is FCL-free); one they flag counts as blocked without asking FCL,
        except within `sphere_first_exact_radius_rad` of the start or a goal (against objects,
        one whose own spheres touch something): queries often begin and end in tight spots.
        That makes a tree edge one compiled call instead of tens of FCL calls, at the price of the narrow passages the spheres over-cover (about
        1.5 cm per link). Every path found this way is FCL-free; it is re-validated regardless.
        When that search fails, the rest of the budget goes to the exact search.
        """
        t0 = time.perf_counter()
        share = self.config.sphere_first_share
        if self.world.has_surface_allowance and self.config.release_map_clearance and share > 0:
            share = self.config.map_clearance_share
        # Not against a bare octree (on MBM clouds without inflation it solved no more than the
        # exact search); a map with its seen voxels and clearance is a sphere world like primitives.
        if (share > 0 and self.world.spheres_usable
                and (not self.world.has_octree or self.world.has_surface_allowance)
                and self.world.sphere_self_overflag() <= MAX_SELF_OVERFLAG):
            # Against objects FCL decides near an anchor only where the spheres flag the anchor
            # itself: near one they clear, spheres and FCL agreed on 99 % of random UR5 states
            # within 0.2 rad on MotionBenchMaker's shelves, and FCL there cost a sixth of a median
            # plan. Not against a map: on the benchmark's cloud maps the median did not drop
            # (8.2 against 7.9 ms; 50 against 48 of 350 problems needed the clearance released).
            anchors = [start, *goals]
            self._anchors = anchors if self.world.has_surface_allowance else [
                q for q in anchors if not self.world.state_free_by_spheres(q, lambda _: False)]
            self._sphere_first = True
            try:
                outcome = self._search(problem, start, goals, is_valid, motion_valid, budget_s * share, rng)
            finally:
                self._sphere_first = False
            outcome = dataclasses.replace(outcome, search="sphere_first")
            if outcome.status is not PlanStatus.TIMEOUT or share >= 1.0:
                return outcome
            spent_s = time.perf_counter() - t0
            if budget_s - spent_s <= 0:
                return outcome
            if self.world.has_surface_allowance and self.config.release_map_clearance:
                return self._surface_search(problem, start, goals, is_valid, motion_valid, budget_s - spent_s, rng,
                                            spent_s)
            # The exact search accepts every state and edge the sphere-first one did: it grows
            # the same trees on (OMPL continues a solve), rather than spending again what they cost.
            exact = self._search(problem, start, goals, is_valid, motion_valid, budget_s - spent_s, rng, resume=True)
            detail = exact.detail if exact.status is PlanStatus.SUCCESS else (
                f"{exact.detail} (after {spent_s:.3f} s of sphere-first search)")
            return dataclasses.replace(exact, detail=detail, search="exact")
        outcome = self._search(problem, start, goals, is_valid, motion_valid, budget_s, rng)
        return dataclasses.replace(outcome, search="exact")

    def _surface_search(self, problem: PlanProblem, start: FloatArray, goals: FloatArray, is_valid: StateValidFn,
                        motion_valid: MotionValidFn, budget_s: float, rng: np.random.Generator,
                        spent_s: float) -> PlanOutcome:
        """Sphere-first search with the map's clearance released everywhere: every state is as
        near an anchor as can be (`surface_allowance.py`), so the padded links keep off the
        seen surface only. Where the cage or shelf is narrower than the clearance allows."""
        self._sphere_first = True
        try:
            with self.world.anchored(self.world.anchors, math.inf):
                # Every state that kept the clearance keeps off the surface: the trees grow on.
                outcome = self._search(problem, start, goals, is_valid, motion_valid, budget_s, rng, resume=True)
        finally:
            self._sphere_first = False
        detail = (f"{outcome.detail}; the map's clearance released after {spent_s:.3f} s"
                  if outcome.status is PlanStatus.SUCCESS else f"{outcome.detail} (after {spent_s:.3f} s with the clearance)")
        return dataclasses.replace(outcome, detail=detail, search="surface")

    def _search(self, problem: PlanProblem, start: FloatArray, goals: FloatArray, is_valid: StateValidFn,
                motion_valid: MotionValidFn, budget_s: float, rng: np.random.Generator, *,
                resume: bool = False) -> PlanOutcome:
        """With `resume`, the first OMPL solve continues the last unsolved one of the same query
        (`OmplSpace.solve`); the caller vouches that the checks now accept all they accepted."""
        t0 = time.perf_counter()
        deadline = t0 + budget_s
        planner_id = problem.planner_id
        direct = next((k for k, g in enumerate(goals) if motion_valid(start, g)), None)
        if direct is not None:
            outcome = self._finish(problem, np.vstack([start, goals[direct]]), goals, motion_valid,
                                   "direct" if planner_id == "auto" else planner_id, time.perf_counter() - t0, rng)
            if outcome.status is PlanStatus.SUCCESS:
                self._remember(outcome.planner_id, True)
                return outcome
            # The segment passed the edge check but not the finer path check: search instead.
        while True:
            # At least a millisecond: the direct check or a failed path may have used the budget up.
            remaining_s = max(deadline - time.perf_counter(), 1e-3)
            if problem.planner_id == "auto":
                planner_id, result = self._auto(start, goals, remaining_s, rng, problem.stop)
            elif planner_id in PLANNER_CLASSES:
                if is_valid is self._is_valid:
                    result = self._space.solve(planner_id, start, goals, time_limit_s=remaining_s, stop=problem.stop,
                                               resume=resume)
                    resume = False  # a path that failed the re-check is drawn afresh
                else:  # workspace bounds: a roadmap checked without them cannot be reused
                    result = self._new_space(is_valid, motion_valid).solve(planner_id, start, goals,
                                                                            time_limit_s=remaining_s,
                                                                            stop=problem.stop)
            else:
                result = self._baseline(planner_id, start, goals, is_valid, motion_valid, remaining_s, rng)
            self._remember(planner_id, result.success)
            if not result.success or result.path is None:
                return PlanOutcome(result.status, result.detail, planner_id=planner_id,
                                   planning_time_s=time.perf_counter() - t0)
            outcome = self._finish(problem, result.path, goals, motion_valid, planner_id, time.perf_counter() - t0, rng)
            # A sampled path that fails the finer re-check is drawn again while time is left (the
            # deterministic baselines would only find the same path).
            if (outcome.status is PlanStatus.SUCCESS or planner_id in BASELINES
                    or time.perf_counter() >= deadline or (problem.stop is not None and problem.stop())):
                return outcome

    def _baseline(self, planner_id: str, start: FloatArray, goals: FloatArray, is_valid: StateValidFn,
                  motion_valid: MotionValidFn,
                  budget_s: float, rng: np.random.Generator) -> PlanResult:
        # Single-goal baselines aim at the goal nearest the start.
        goal = goals[int(np.argmin(np.linalg.norm(goals - start, axis=1)))]
        common = dict(lower_rad=self.robot.lower_limits_rad, upper_rad=self.robot.upper_limits_rad,
                      is_valid=is_valid, motion_valid=motion_valid)
        if planner_id in ("astar", "dijkstra"):
            return plan_lattice(start, goal, **common, resolution_rad=self.config.lattice_resolution_rad,
                                heuristic_weight=1.0 if planner_id == "astar" else 0.0, time_limit_s=budget_s)
        return plan_potential_field(start, goal, **common, clearance_m=self.world.clearance_m, rng=rng,
                                    config=PotentialFieldConfig(time_limit_s=budget_s, max_escapes=10))

    def auto_candidates(self, start: FloatArray, goals: FloatArray, rng: np.random.Generator) -> list[str]:
        """The planners `auto` runs for this query, first the one it trusts most.

        RRT-Connect is the default. A warm PRM roadmap on this world answers in a few graph
        searches, so PRM joins the race when it has one and has not been failing. Clutter near
        the start or a goal (random states within 0.1 rad of it in collision) is where
        RRT-Connect's greedy extensions struggle, so BIT*'s informed batch search joins then.
        Planners that failed their last three queries on this world while another succeeded
        are left out.
        """
        candidates = ["rrtconnect"]
        if self._space.roadmap_size("prm") > 0:
            candidates.append("prm")
        if self._cluttered(start, rng) or any(self._cluttered(g, rng) for g in goals[:3]):
            candidates.append("bitstar")
        failing = {p for p, h in self._history.items() if len(h) >= 3 and not any(list(h)[-3:])}
        working = [p for p in candidates if p not in failing]
        return working or candidates

    def _auto(self, start: FloatArray, goals: FloatArray, budget_s: float, rng: np.random.Generator,
              stop: Callable[[], bool] | None = None) -> tuple[str, PlanResult]:
        candidates = self.auto_candidates(start, goals, rng)
        if len(candidates) == 1:
            return candidates[0], self._space.solve(candidates[0], start, goals, time_limit_s=budget_s, stop=stop)
        return race(self._space, candidates, start, goals, time_limit_s=budget_s)

    def _cluttered(self, q: FloatArray, rng: np.random.Generator, probes: int = 8, spread_rad: float = 0.1) -> bool:
        low = np.maximum(q - spread_rad, self.robot.lower_limits_rad)
        high = np.minimum(q + spread_rad, self.robot.upper_limits_rad)
        return any(not self._is_valid(p) for p in rng.uniform(low, high, size=(probes, q.shape[0])))

    def _remember(self, planner_id: str, success: bool) -> None:
        self._history.setdefault(planner_id, deque(maxlen=_AUTO_HISTORY)).append(success)

    def _finish(self, problem: PlanProblem, path: FloatArray, goals: FloatArray, motion_valid: MotionValidFn,
                planner_id: str, planning_time_s: float, rng: np.random.Generator) -> PlanOutcome:
        simplify_start = time.perf_counter()
        raw = path
        checked: set[bytes] = set()
        if problem.simplify and len(path) > 2:
            path = shortcut_path(path, motion_valid=recording(motion_valid, checked), rng=rng,
                                 iterations=self.config.shortcut_iterations, patience=self.config.shortcut_patience)
        simplification_time_s = time.perf_counter() - simplify_start
        # Re-validate what we return, exactly: a path is only as good as its last check. The
        # shortcut keeps pieces of checked segments unchecked, so when its path fails, the
        # search's own path (every segment checked) is the fallback.
        sphere_first, self._sphere_first = self._sphere_first, False
        candidates = [path] if path is raw else [path, raw]
        try:
            path = next((p for p in candidates if path_rechecked(
                self.world, p, motion_valid, checked, path_check_rad=self.config.path_check_resolution_rad,
                edge_rad=self.config.edge_resolution_rad, own_check=motion_valid is self._motion_valid)), None)
        finally:
            self._sphere_first = sphere_first
        if path is None:
            return PlanOutcome(PlanStatus.TIMEOUT, "the found path failed re-validation", planner_id=planner_id,
                               planning_time_s=planning_time_s)
        goal_index = int(np.argmin(np.max(np.abs(goals - path[-1]), axis=1)))
        return PlanOutcome(
            PlanStatus.SUCCESS, "ok", path=path, planner_id=planner_id, planning_time_s=planning_time_s,
            simplification_time_s=simplification_time_s, path_length_rad=path_length_rad(path),
            max_joint_step_rad=max_joint_step_rad(path),
            min_clearance_m=self._sampled_clearance_m(path) if self.config.report_clearance else float("inf"),
            goal_index=goal_index)

    def _sampled_clearance_m(self, path: FloatArray) -> float:
        """Clearance at the waypoints and evenly spread states between them.

        FCL's octree distance costs ~10 ms per Panda state, so the exact minimum over a finely
        interpolated path would cost seconds; this reports the minimum over at most
        `CLEARANCE_SAMPLES` states (the path itself is collision-checked finely regardless).
        """
        dense = interpolate_path(path, self.config.edge_resolution_rad)
        if len(dense) > CLEARANCE_SAMPLES:
            dense = dense[np.linspace(0, len(dense) - 1, CLEARANCE_SAMPLES).round().astype(int)]
        return self.world.min_clearance_m(dense)
