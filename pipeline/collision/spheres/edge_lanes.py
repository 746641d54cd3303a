"""An edge's states through the sphere broad phase, `LANES` at a time, each at its own clearance.

The straight joint-space segment from a to b is cut into `steps` intervals; its states are
visited in `CollisionWorld.motion_valid` order (b, the interior in bisection order, a) and go
through `lanes_suspect` in chunks of `LANES`. Near a query's start and goals a map's clearance
shrinks with the joint-space distance to the nearest anchor (`surface_allowance.py`); each
lane's tier, and with it the clearance its spheres keep from the occupied voxels, is worked out
here per state. Checking the whole edge at its strictest tier instead flagged every state of an
edge leaving a goal that lies near a surface, and each flagged state was checked again on its
own from Python at its own tier.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from robonav.pipeline.collision.spheres.lanes import LANES, VECTOR, LaneWorld, lanes_suspect
from robonav.pipeline.types import FloatArray, IntArray


@nb.njit(cache=True)
def state_tier(q_lanes: FloatArray, w: int, anchors: FloatArray, radius_sq: float, tiers: int) -> int:  # pragma: no cover
    """The clearance tier of lane w's state: t in [0, tiers) within radius_sq of an anchor
    (`surface_allowance.clearance_tier`), -1 from there on or without anchors."""
    nearest_sq = math.inf
    for m in range(anchors.shape[0]):
        total = 0.0
        for j in range(anchors.shape[1]):
            offset = anchors[m, j] - q_lanes[j, w]
            total += offset * offset
        nearest_sq = min(nearest_sq, total)
    if tiers < 1 or nearest_sq >= radius_sq:
        return -1
    return min(tiers - 1, int(tiers * math.sqrt(nearest_sq / radius_sq)))


@nb.njit(cache=True)
def state_suspect_tiered(q: FloatArray, world: LaneWorld, anchors: FloatArray,
                         radius_sq: float) -> tuple[bool, int]:  # pragma: no cover
    """(whether a sphere at the one state `q` (dof,) is within contact, the state's tier), lane 0
    alone. With anchors (K, dof), K > 0, the state keeps its tier's clearance as an edge's state
    does (`edge_suspect_steps`); without, world.grid_clearance, and its tier reads -1."""
    cos_lanes, sin_lanes, q_lanes = world.cos_lanes, world.sin_lanes, world.q_lanes
    for j in range(q.shape[0]):
        cos_lanes[j, 0], sin_lanes[j, 0], q_lanes[j, 0] = math.cos(q[j]), math.sin(q[j]), q[j]
    tier = -1
    if anchors.shape[0] > 0:
        tiers = world.tier_clearance.shape[0] - 1
        tier = state_tier(q_lanes, 0, anchors, radius_sq, tiers)
        world.lane_clearance[0] = world.tier_clearance[tier] if tier >= 0 else world.tier_clearance[tiers]
    else:
        world.lane_clearance[0] = world.grid_clearance
    lanes_suspect(1, world, True)
    return world.flags[0], tier


@nb.njit(cache=True)
def edge_suspect_steps(a: FloatArray, b: FloatArray, resolution: float, first_only: bool, out: IntArray,
                       queue: IntArray, world: LaneWorld, anchors: FloatArray, radius_sq: float,
                       checked_resolution: float) -> tuple[int, int]:  # pragma: no cover
    """(count of suspects written to `out`, steps), or (-1, steps) when `out` and `queue` have
    fewer than 2 * steps + 2 rows. See `SphereBroadPhase.edge_suspects`.

    A suspect's row of `out` (M, 2) holds its step and its tier. With anchors (K, dof), K > 0,
    a state of tier t keeps world.tier_clearance[t] from the voxels and one of tier -1 the last
    entry (tier_clearance has tiers + 1 entries); without, every state keeps
    world.grid_clearance and its tier reads -1.

    With checked_resolution > 0, the edge's states at that resolution are known free: those of
    its own states that are among them (k = 0, m, 2m ..., m = steps / gcd(steps, their count))
    are skipped."""
    dof = a.shape[0]
    longest = 0.0
    for j in range(dof):
        longest = max(longest, abs(b[j] - a[j]))
    steps = max(1, int(math.ceil(longest / resolution - 1e-9)))
    known_every = 0
    if checked_resolution > 0:
        checked = max(1, int(math.ceil(longest / checked_resolution - 1e-9)))
        known_every = steps // math.gcd(steps, checked)
    if out.shape[0] < 2 * steps + 2 or queue.shape[0] < 2 * steps + 2:
        return -1, steps
    # cos and sin of every state's joints by a rotation per step (a sine and a cosine per joint
    # and state cost a third of the kinematics), taken afresh every 16 steps against drift.
    trig = np.empty((steps + 1, 2, dof))
    for j in range(dof):
        step = (b[j] - a[j]) / steps
        c_step, s_step = math.cos(step), math.sin(step)
        c = s = 0.0
        for k in range(steps + 1):
            if k % 16 == 0:
                angle = a[j] + (b[j] - a[j]) * (k / steps)
                c, s = math.cos(angle), math.sin(angle)
            else:
                c, s = c * c_step - s * s_step, s * c_step + c * s_step
            trig[k, 0, j], trig[k, 1, j] = c, s
    # Visiting order of CollisionWorld.motion_valid: b, interior in bisection (breadth-first) order, a.
    order = queue[:, 0]
    spans = queue[:, 1]
    n_order = 0
    order[n_order] = steps
    n_order += 1
    # The FIFO of (lo, hi) spans lives in queue[:, 1] as lo * (steps + 1) + hi.
    head, tail = 0, 1
    spans[0] = steps  # lo = 0, hi = steps
    while head < tail:
        lo, hi = spans[head] // (steps + 1), spans[head] % (steps + 1)
        head += 1
        if hi - lo < 2:
            continue
        mid = (lo + hi) // 2
        order[n_order] = mid
        n_order += 1
        spans[tail] = lo * (steps + 1) + mid
        spans[tail + 1] = mid * (steps + 1) + hi
        tail += 2
    order[n_order] = 0
    n_order += 1
    if known_every > 0:
        kept = 0
        for i in range(n_order):
            if order[i] % known_every != 0:
                order[kept] = order[i]
                kept += 1
        n_order = kept
    cos_lanes, sin_lanes, q_lanes, flags = world.cos_lanes, world.sin_lanes, world.q_lanes, world.flags
    lane_clearance, lane_tier, tier_clearance = world.lane_clearance, world.lane_tier, world.tier_clearance
    tiers = tier_clearance.shape[0] - 1
    anchored = anchors.shape[0] > 0
    count = 0
    for first in range(0, n_order, LANES):
        n = min(LANES, n_order - first)
        # A short chunk is padded to a whole number of vectors (VECTOR lanes) with copies.
        lanes = min(LANES, (n + VECTOR - 1) // VECTOR * VECTOR)
        for w in range(lanes):
            k = order[first + min(w, n - 1)]
            t = k / steps
            for j in range(dof):
                cos_lanes[j, w], sin_lanes[j, w] = trig[k, 0, j], trig[k, 1, j]
                q_lanes[j, w] = a[j] + (b[j] - a[j]) * t
            if anchored:
                lane_tier[w] = state_tier(q_lanes, w, anchors, radius_sq, tiers)
                lane_clearance[w] = tier_clearance[lane_tier[w]] if lane_tier[w] >= 0 else tier_clearance[tiers]
            else:
                lane_tier[w] = -1
                lane_clearance[w] = world.grid_clearance
        lanes_suspect(lanes, world, first_only)
        for w in range(n):
            if flags[w]:
                out[count, 0] = order[first + w]
                out[count, 1] = lane_tier[w]
                count += 1
                if first_only:
                    return count, steps
    return count, steps
