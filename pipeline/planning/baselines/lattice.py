"""A* and Dijkstra search on a regular joint-space lattice anchored at the start.

The lattice holds `q_start + resolution_rad * k` for integer vectors `k` within the joint
bounds; each node has 2n neighbours (one joint moved by +-resolution). The goal, which is in
general off the lattice, is connected by one straight segment from any expanded node within
`resolution_rad` of it in every joint. Costs are L1 (Manhattan) joint-space lengths: a lattice
move costs `resolution_rad`, the goal segment its L1 length. The heuristic is
`heuristic_weight * |q - q_goal|_1`, consistent for weights <= 1, so A* (weight 1) returns a
path exactly as short on this lattice as Dijkstra (weight 0); weights > 1 give weighted A*
(faster, up to `weight` times longer). With L1 costs the direct segment is a shortest path, so
it is tried first.

Edges are checked lazily: a node is pushed without any check and its incoming edge is checked
with `motion_valid` only when it is popped (node validity is cached, so a colliding node costs
one `is_valid` call however many parents reach it). Nothing is pruned by tentative cost, so a
node whose cheapest edge turns out blocked can still be reached through another parent.

Why this scales badly with the number of joints n:

- Branching is 2n (14 for the Panda) and a detour of d lattice steps around an obstacle
  explores the lattice "ball" of radius d, which holds on the order of (2d)^n / n! nodes.
  Admissible A* cannot pass a wall without expanding every node whose f is below the optimal
  cost, and with the L1 heuristic on a 7-D lattice there are enormous plateaus of equal f.
- The state count grows as (range / resolution)^n: the Panda's joint box at 0.1 rad holds
  6 x 10^11 nodes, so no search is exhaustive and "no path" is indistinguishable from "not
  yet found" (both return TIMEOUT here).
- Measured on the Panda (pybullet_data URDF, padding 0.01 m, `CollisionWorld.motion_valid`
  at 0.02 rad, 0.1 rad lattice, joint 1 from -1 to +1 rad at the home pose; 700-1,100
  expansions/s, each paying 14 pushes and one FCL edge check of ~6 states), A* (w = 1) vs
  weighted A* (w = 2):

  | obstacle                                | detour (L1) | A* expansions  | w = 2 expansions |
  | --------------------------------------- | ----------- | -------------- | ---------------- |
  | 8 cm cube under the hand (test problem) | +0.2 rad    | 32 (0.02 s)    | 22               |
  | 20 cm cube                              | +0.6 rad    | 1,354 (1.2 s)  | 286 (0.2 s)      |
  | tall pillar r = 2 cm on the hand circle | +0.6 rad    | 2,250 (~4 s)   | 444 (~1 s)       |
  | tall pillar r = 5 cm                    | +0.8 rad    | 5,852 (5-13 s) | 1,601 (1.4-3 s)  |
  | tall pillar r = 8 cm                    | <= +1.0 rad | > 12,199: TIMEOUT at 30 s | 5,047 (9.8 s) |
  | tall pillar r = 12 cm                   | ?           | TIMEOUT at 30 s | TIMEOUT at 30 s |
  | reach under a 40x80 cm plate (IK goal)  | ?           | TIMEOUT at 30 s (20 k) | TIMEOUT (17 k); w = 5 too |

  Each extra pair of detour steps multiplies A*'s work by about 2.5; RRTConnect solves the
  plate problem in 0.07 s. On the 2-D point robot the same code solves a 100 x 100 lattice
  around a wall with 4,000 expansions in 0.25 s (Dijkstra: 9,100 in 0.56 s).

So this is a baseline and a teaching tool, not the production planner: it is optimal and
resolution-complete, but only practical in few dimensions or for small detours.
"""

from __future__ import annotations

import heapq
import itertools
import math
import time
from collections.abc import Callable

import numpy as np

from robonav.pipeline.planning.inputs import bounds_violation, joint_vector
from robonav.pipeline.planning.result import PlanResult, PlanStatus
from robonav.pipeline.types import FloatArray, MotionValidFn, StateValidFn

_GOAL = None
"""Heap marker of the goal node (it has no lattice coordinates)."""


def plan_lattice(
    q_start: FloatArray,
    q_goal: FloatArray,
    *,
    lower_rad: FloatArray,
    upper_rad: FloatArray,
    is_valid: StateValidFn,
    motion_valid: MotionValidFn,
    resolution_rad: float,
    heuristic_weight: float = 1.0,
    time_limit_s: float = 1.0,
    max_expansions: int = 1_000_000,
) -> PlanResult:
    """Plan a joint-space path on a lattice with A* (`heuristic_weight=1`) or Dijkstra (0).

    Args:
        q_start: (n,) start configuration [rad]; the lattice is anchored here.
        q_goal: (n,) goal configuration [rad].
        lower_rad: (n,) lower joint bounds [rad].
        upper_rad: (n,) upper joint bounds [rad], each > the lower bound.
        is_valid: State validity of an (n,) array.
        motion_valid: Validity of the straight segment between two (n,) states, both ends included.
        resolution_rad: Lattice spacing in every joint [rad], > 0.
        heuristic_weight: Multiplier of the L1 distance-to-goal heuristic, >= 0: 0 is Dijkstra,
            1 is A* (optimal on the lattice), > 1 is weighted A*.
        time_limit_s: Search budget [s], > 0.
        max_expansions: Largest number of nodes expanded, >= 1.

    Returns:
        A `PlanResult`; on SUCCESS its path is (K, n), K >= 2, from exactly `q_start` through
        lattice nodes to exactly `q_goal`, every segment accepted by `motion_valid`. TIMEOUT
        when the budget runs out, and also when the reachable lattice is exhausted (the detail
        says which).

    Raises:
        ValueError: wrong shapes, non-finite values, empty bounds, or a non-positive
            resolution, budget or negative weight.
    """
    t0 = time.perf_counter()
    lower = joint_vector(lower_rad, "lower_rad")
    n = lower.shape[0]
    upper = joint_vector(upper_rad, "upper_rad", n)
    start = joint_vector(q_start, "q_start", n)
    goal = joint_vector(q_goal, "q_goal", n)
    for i in range(n):
        if not lower[i] < upper[i]:
            raise ValueError(f"lower_rad[{i}] = {lower[i]} must be < upper_rad[{i}] = {upper[i]}")
    if not (math.isfinite(resolution_rad) and resolution_rad > 0):
        raise ValueError(f"resolution_rad must be finite and > 0, got {resolution_rad}")
    if not (math.isfinite(heuristic_weight) and heuristic_weight >= 0):
        raise ValueError(f"heuristic_weight must be finite and >= 0, got {heuristic_weight}")
    if not (math.isfinite(time_limit_s) and time_limit_s > 0):
        raise ValueError(f"time_limit_s must be finite and > 0, got {time_limit_s}")
    if isinstance(max_expansions, bool) or not isinstance(max_expansions, (int, np.integer)) or max_expansions < 1:
        raise ValueError(f"max_expansions must be an integer >= 1, got {max_expansions!r}")

    def done(status: PlanStatus, detail: str, path: FloatArray | None = None) -> PlanResult:
        return PlanResult(status, path, detail, time.perf_counter() - t0)

    for label, q in (("start", start), ("goal", goal)):
        problem = bounds_violation(q, lower, upper)
        if problem:
            return done(PlanStatus.OUT_OF_BOUNDS, f"{label}: {problem}")
    if not is_valid(start):
        return done(PlanStatus.START_INVALID, "start state is invalid (e.g. in collision)")
    if not is_valid(goal):
        return done(PlanStatus.GOAL_INVALID, "goal state is invalid (e.g. in collision)")
    if motion_valid(start, goal):
        return done(PlanStatus.SUCCESS, "direct segment from start to goal is valid", np.vstack([start, goal]))

    # Integer lattice coordinates of the bounds: node k is valid when k_lo <= k <= k_hi.
    k_lo = np.ceil((lower - start) / resolution_rad - 1e-9).astype(np.int64)
    k_hi = np.floor((upper - start) / resolution_rad + 1e-9).astype(np.int64)
    k_lo_t, k_hi_t = tuple(int(v) for v in k_lo), tuple(int(v) for v in k_hi)
    goal_reach = resolution_rad * (1 + 1e-9)

    def state(key: tuple[int, ...]) -> FloatArray:
        return np.clip(start + resolution_rad * np.array(key, dtype=np.float64), lower, upper)

    def heuristic(q: FloatArray) -> float:
        return heuristic_weight * float(np.sum(np.abs(q - goal)))

    start_minus_goal = [float(v) for v in start - goal]
    origin = (0,) * n
    counter = itertools.count()
    # Entries: (f, -g, tie, node, parent). -g breaks f ties towards deeper nodes (fewer
    # expansions on the L1 plateaus); `tie` keeps the order deterministic.
    heap: list[tuple[float, float, int, tuple[int, ...] | None, tuple[int, ...] | None]] = [
        (heuristic(start), -0.0, next(counter), origin, None)
    ]
    parents: dict[tuple[int, ...], tuple[int, ...] | None] = {}  # closed set: node -> parent
    node_valid: dict[tuple[int, ...], bool] = {origin: True}
    expansions = 0
    edge_checks = 0
    while heap:
        if expansions >= max_expansions:
            return done(PlanStatus.TIMEOUT, f"no path within {max_expansions} expansions "
                        f"({len(parents)} nodes closed, {edge_checks} edge checks)")
        if time.perf_counter() - t0 > time_limit_s:
            return done(PlanStatus.TIMEOUT, f"no path within {time_limit_s:.3f} s "
                        f"({expansions} expansions, {edge_checks} edge checks)")
        f, neg_g, _, node, parent = heapq.heappop(heap)
        g = -neg_g
        if node is _GOAL:
            assert parent is not None
            edge_checks += 1
            if motion_valid(state(parent), goal):
                path = _trace(parents, parent, state)
                path.append(goal)
                return done(PlanStatus.SUCCESS, f"lattice path of {len(path)} waypoints, L1 cost {g:.6g} rad "
                            f"({expansions} expansions, {edge_checks} edge checks)", np.array(path))
            continue
        if node in parents:
            continue
        if parent is not None:
            if not node_valid.setdefault(node, bool(is_valid(state(node)))):
                continue
            edge_checks += 1
            if not motion_valid(state(parent), state(node)):
                continue
        parents[node] = parent
        expansions += 1
        q = state(node)
        if float(np.max(np.abs(q - goal))) <= goal_reach:
            cost = g + float(np.sum(np.abs(q - goal)))
            heapq.heappush(heap, (cost, -cost, next(counter), _GOAL, node))
        # The heuristic changes in one term per move: update it in plain floats (no arrays).
        h_node = heuristic(q)
        g_next = g + resolution_rad
        for axis in range(n):
            here = heuristic_weight * abs(start_minus_goal[axis] + resolution_rad * node[axis])
            for step in (-1, 1):
                k = node[axis] + step
                if k < k_lo_t[axis] or k > k_hi_t[axis]:
                    continue
                neighbour = node[:axis] + (k,) + node[axis + 1:]
                if neighbour in parents or node_valid.get(neighbour) is False:
                    continue
                there = heuristic_weight * abs(start_minus_goal[axis] + resolution_rad * k)
                heapq.heappush(heap, (g_next + h_node - here + there, -g_next, next(counter), neighbour, node))
    return done(PlanStatus.TIMEOUT, f"no path on the lattice at resolution {resolution_rad:.4g} rad: all "
                f"{len(parents)} reachable nodes expanded ({edge_checks} edge checks)")


def _trace(parents: dict[tuple[int, ...], tuple[int, ...] | None], last: tuple[int, ...],
           state: Callable[[tuple[int, ...]], FloatArray]) -> list[FloatArray]:
    """States from the lattice origin (the start, exactly) to `last`."""
    keys: list[tuple[int, ...]] = []
    key: tuple[int, ...] | None = last
    while key is not None:
        keys.append(key)
        key = parents[key]
    keys.reverse()
    return [state(k) for k in keys]
