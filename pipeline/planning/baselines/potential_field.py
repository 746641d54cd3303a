"""Artificial potential field planner in joint space, with random-walk escapes from local minima.

The planner descends `U(q) = U_att(q) + U_rep(q)` in fixed-length steps:

- Attraction to the goal, quadratic near it and conic far away (so far-away goals do not
  dominate the repulsion): with `e = |q - q_goal|` (Euclidean, rad),
  `U_att = 0.5 k_att e^2` for `e <= r_c`, else `k_att (r_c e - 0.5 r_c^2)`.
- Repulsion from obstacles through a clearance function `d(q)` [m] (e.g.
  `CollisionWorld.clearance_m`): `U_rep = 0.5 k_rep (1/d - 1/d_0)^2` for `d < d_0` (the
  influence distance), else 0.
- Gradient of `d(q)` by central finite differences in joint space (2n clearance calls per step,
  only inside the influence distance). Chosen over workspace points with Jacobians because it
  keeps the planner a function of callables (it runs on a 2-D point robot in tests) and uses
  the clearance the collision world already has. The price: `clearance_m` is a minimum over
  link/obstacle pairs, so its gradient is the nearest pair's only and jumps where the nearest
  pair changes (the descent can chatter there), and on the Panda it costs 2n = 14 FCL distance
  queries per step.
- Each step moves `step_rad` along the negative gradient (normalised), clamped to the bounds,
  and is kept only if `motion_valid` accepts it (halved up to three times otherwise). Within
  `max(goal_tolerance_rad, step_rad)` of the goal the straight segment to the goal is tried.
- A local minimum is declared when the net displacement over the last `stall_window` steps is
  below `stall_window * step_rad / 10`, or no step is valid. Then, while escapes remain, a
  seeded random walk (`escape_steps`, doubling with each escape, every step checked with
  `motion_valid`) moves the robot away and the descent resumes (Barraquand and Latombe's
  randomized path planner). The random walk stays in the returned path.

Where it gets stuck (measured; 2-D: step 0.01, influence 0.1 m; Panda: step 0.05 rad,
influence 0.15 m, `CollisionWorld.clearance_m`, motion checks at 0.02 rad):

- 2-D point robot, a wall across the line from start to goal: stuck in front of it (at
  x = 0.37 for a wall face at x = 0.45) whenever the face the robot meets is flat and
  perpendicular to the attraction, symmetric or not: the clearance gradient of a flat face has
  no sideways component. An obstacle only partly across the line (off-center) is slid past.
- 2-D U-shaped trap (a cup open towards the start, its bottom across the line): the classic
  trap. Plain descent stops at the cup's bottom after 61 steps (0.02 s, TIMEOUT "local
  minimum"). With random walks of 0.1 rad steps (20 steps, doubling) and up to 8 escapes,
  20 of 20 seeds escaped, using 1-6 escapes (0.06-0.08 s); with 0.02 rad walk steps only 13
  of 20 did: a walk must leave the basin of the trap, about `escape_step_rad * sqrt(L)`.
- Panda, joint 1 from -1 to +1 rad at the home pose: free space 38 steps (0.09 s); past an
  8 cm cube 40 steps (0.3 s, 9 cm minimum clearance); around a tall pillar on the hand's
  circle of radius 5, 8 and 12 cm it does NOT get stuck (107-145 steps, 0.4-0.9 s): seven
  joints give the repulsion room to push the arm over or around. A 0.7 m high radial wall:
  past it in 90 steps.
- Panda reaching under a 40 x 80 cm plate (start: hand above it pointing down; goal: hand
  below it pointing forward, both from `ik.solve_ik`): stuck after 100 steps (0.2-0.35 s)
  0.72 rad from the goal with the hand still above the plate (z = 0.58 m; the goal has it
  at 0.20 m, below the plate at 0.35 m). With 6-8 random walks of 0.2 rad
  steps it did not escape for any of 4 seeds (5,000 steps, 4-14 s; long walks wander up to
  5 rad away). RRTConnect solves it in 0.07 s.
- Cost: each Panda step inside the influence distance is 2n + 1 = 15 clearance calls
  (70-500 us each with a few primitives, depending on load) plus one edge check: 3-9 ms.

Use it as a local planner or baseline; it is not complete.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from robonav.pipeline.planning.inputs import bounds_violation, joint_vector
from robonav.pipeline.planning.result import PlanResult, PlanStatus
from robonav.pipeline.types import ClearanceFn, FloatArray, MotionValidFn, StateValidFn

_STALL_FRACTION = 0.1
"""Stuck when the net move over `stall_window` steps is below this fraction of their length."""
_STEP_HALVINGS = 3
"""Times a blocked step is halved before the state counts as a local minimum."""
_WALK_TRIES_PER_STEP = 4
"""Random-walk proposals per accepted random-walk step before the walk is cut short."""


@dataclass(frozen=True)
class PotentialFieldConfig:
    """Tuning of `plan_potential_field`; validated on construction."""

    step_rad: float = 0.05
    """Length of one descent or random-walk step (Euclidean, joint space) [rad]."""
    goal_tolerance_rad: float = 0.1
    """Within this Euclidean distance of the goal the straight segment to it is tried [rad]."""
    attractive_gain: float = 1.0
    """k_att of the attractive potential [1/rad^2]."""
    conic_radius_rad: float = 0.5
    """r_c: the attraction is quadratic within this distance of the goal, conic beyond [rad]."""
    repulsive_gain: float = 1e-3
    """k_rep of the repulsive potential [m^2] (relative to k_att: what matters is the ratio)."""
    influence_distance_m: float = 0.1
    """d_0: obstacles farther than this clearance do not repel [m]."""
    gradient_step_rad: float = 1e-3
    """Finite-difference step of the clearance gradient [rad]."""
    stall_window: int = 20
    """Steps over which too little net motion means a local minimum."""
    max_escapes: int = 0
    """Random walks allowed after local minima (0: report the first local minimum)."""
    escape_steps: int = 20
    """Steps of the first random walk; each later walk is twice as long as the one before."""
    escape_step_rad: float = 0.1
    """Length of one random-walk step (Euclidean, joint space) [rad]; a walk of L steps moves
    about `escape_step_rad * sqrt(L)` away, so this should be comparable to the trap's size."""
    max_steps: int = 5000
    """Budget of descent plus random-walk steps."""
    time_limit_s: float = 5.0
    """Wall-clock budget [s]."""

    def __post_init__(self) -> None:
        for name in ("step_rad", "escape_step_rad", "goal_tolerance_rad", "attractive_gain",
                     "conic_radius_rad", "influence_distance_m", "gradient_step_rad", "time_limit_s"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"potential field {name} must be finite and > 0, got {value!r}")
        if not (math.isfinite(self.repulsive_gain) and self.repulsive_gain >= 0):
            raise ValueError(f"potential field repulsive_gain must be finite and >= 0, got {self.repulsive_gain!r}")
        for name, least in (("stall_window", 2), ("max_escapes", 0), ("escape_steps", 1), ("max_steps", 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < least:
                raise ValueError(f"potential field {name} must be an integer >= {least}, got {value!r}")


def plan_potential_field(
    q_start: FloatArray,
    q_goal: FloatArray,
    *,
    lower_rad: FloatArray,
    upper_rad: FloatArray,
    is_valid: StateValidFn,
    motion_valid: MotionValidFn,
    clearance_m: ClearanceFn,
    rng: np.random.Generator,
    config: PotentialFieldConfig | None = None,
) -> PlanResult:
    """Descend an attractive + repulsive potential from `q_start` to `q_goal`.

    Args:
        q_start: (n,) start configuration [rad].
        q_goal: (n,) goal configuration [rad].
        lower_rad: (n,) lower joint bounds [rad].
        upper_rad: (n,) upper joint bounds [rad], each > the lower bound.
        is_valid: State validity of an (n,) array (start and goal are checked with it).
        motion_valid: Validity of the straight segment between two (n,) states, both ends included.
        clearance_m: Distance [m] from the robot at an (n,) state to the nearest obstacle
            (0 in contact, +inf with no obstacles).
        rng: Source of the random-walk directions.
        config: Tuning; None takes `PotentialFieldConfig()`.

    Returns:
        A `PlanResult`; on SUCCESS its path is (K, n), K >= 2, from exactly `q_start` to exactly
        `q_goal`, every segment accepted by `motion_valid` (often many short steps: shortcut it
        before execution). A local minimum with no escapes left is TIMEOUT with a detail that
        starts "local minimum at"; so is an exhausted step or time budget (detail "budget").

    Raises:
        ValueError: wrong shapes, non-finite values or empty bounds.
    """
    t0 = time.perf_counter()
    cfg = PotentialFieldConfig() if config is None else config
    lower = joint_vector(lower_rad, "lower_rad")
    n = lower.shape[0]
    upper = joint_vector(upper_rad, "upper_rad", n)
    start = joint_vector(q_start, "q_start", n)
    goal = joint_vector(q_goal, "q_goal", n)
    for i in range(n):
        if not lower[i] < upper[i]:
            raise ValueError(f"lower_rad[{i}] = {lower[i]} must be < upper_rad[{i}] = {upper[i]}")

    def done(status: PlanStatus, detail: str, path: list[FloatArray] | None = None) -> PlanResult:
        return PlanResult(status, None if path is None else np.array(path), detail, time.perf_counter() - t0)

    for label, q in (("start", start), ("goal", goal)):
        problem = bounds_violation(q, lower, upper)
        if problem:
            return done(PlanStatus.OUT_OF_BOUNDS, f"{label}: {problem}")
    if not is_valid(start):
        return done(PlanStatus.START_INVALID, "start state is invalid (e.g. in collision)")
    if not is_valid(goal):
        return done(PlanStatus.GOAL_INVALID, "goal state is invalid (e.g. in collision)")

    def gradient(q: FloatArray) -> FloatArray:
        offset = q - goal
        distance = float(np.linalg.norm(offset))
        grad = cfg.attractive_gain * (offset if distance <= cfg.conic_radius_rad
                                      else cfg.conic_radius_rad * offset / distance)
        if cfg.repulsive_gain == 0:
            return grad
        d = float(clearance_m(q))
        if not d < cfg.influence_distance_m:
            return grad
        d = max(d, 1e-6)
        h = cfg.gradient_step_rad
        d_grad = np.empty(n)
        for i in range(n):
            # One-sided at a bound, so the probes stay inside the joint box.
            plus, minus = q.copy(), q.copy()
            plus[i] = min(q[i] + h, upper[i])
            minus[i] = max(q[i] - h, lower[i])
            d_grad[i] = (float(clearance_m(plus)) - float(clearance_m(minus))) / (plus[i] - minus[i])
        d_grad[~np.isfinite(d_grad)] = 0.0
        return grad - cfg.repulsive_gain * (1.0 / d - 1.0 / cfg.influence_distance_m) / (d * d) * d_grad

    path: list[FloatArray] = [start]
    q = start
    steps = 0
    escapes = 0
    stall_distance = cfg.stall_window * cfg.step_rad * _STALL_FRACTION
    window_start = 0  # index in `path` where the current stall window starts
    while True:
        if np.linalg.norm(q - goal) <= max(cfg.goal_tolerance_rad, cfg.step_rad) and motion_valid(q, goal):
            path.append(goal)
            return done(PlanStatus.SUCCESS, f"potential field: {len(path)} waypoints, {steps} steps, "
                        f"{escapes} random-walk escape(s)", path)
        if steps >= cfg.max_steps or time.perf_counter() - t0 > cfg.time_limit_s:
            return done(PlanStatus.TIMEOUT, f"budget of {cfg.max_steps} steps / {cfg.time_limit_s:.3f} s "
                        f"exhausted after {steps} steps and {escapes} escape(s), "
                        f"{np.linalg.norm(q - goal):.4g} rad from the goal")
        grad = gradient(q)
        norm = float(np.linalg.norm(grad))
        moved = False
        if norm > 0 and math.isfinite(norm):
            length = cfg.step_rad
            for _ in range(_STEP_HALVINGS + 1):
                candidate = np.clip(q - length * grad / norm, lower, upper)
                if np.any(candidate != q) and motion_valid(q, candidate):
                    q, moved = candidate, True
                    break
                length *= 0.5
        if moved:
            steps += 1
            path.append(q)
            stalled = (len(path) - window_start > cfg.stall_window
                       and np.linalg.norm(q - path[-1 - cfg.stall_window]) < stall_distance)
        else:
            stalled = True
        if not stalled:
            continue
        if escapes >= cfg.max_escapes:
            return done(PlanStatus.TIMEOUT, f"local minimum at q = {np.array2string(q, precision=4)} "
                        f"({np.linalg.norm(q - goal):.4g} rad from the goal) after {steps} steps and "
                        f"{escapes} random-walk escape(s)")
        walk_length = cfg.escape_steps * 2**escapes
        escapes += 1
        accepted = 0
        for _ in range(walk_length * _WALK_TRIES_PER_STEP):
            if accepted >= walk_length or steps >= cfg.max_steps:
                break
            direction = rng.normal(size=n)
            candidate = np.clip(q + cfg.escape_step_rad * direction / np.linalg.norm(direction), lower, upper)
            if np.any(candidate != q) and motion_valid(q, candidate):
                q = candidate
                path.append(q)
                accepted += 1
                steps += 1
        window_start = len(path) - 1
