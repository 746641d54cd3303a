"""Leaving a start that is inside the robot's padding around the occupancy map.

An arm that braked in front of a newly seen obstacle, or whose map grew by a few noisy voxels,
often rests with a padded link just inside the inflated map. It touches nothing, but every plan
from there is START_IN_COLLISION and the arm is stuck. MoveIt's planning pipeline handles this
with its FixStartStateCollision adapter: it samples states near the start ("jiggles", by default
within 2 % of each joint range, up to 100 samples), plans from the first valid one and puts the
real start in front of the path, without checking that first segment.

This does the same with one rule more, so that the way out is still collision-checked: only
occupancy pairs may be in collision at the start, and from the start through every state of the
straight segment to the escape state the arm must keep off what the cameras saw. When the
world knows the voxels the sensors saw before the map was inflated (`seen_voxels_m`), the
padded links must not touch those; otherwise the bare (unpadded) links must not touch the
inflated map. Objects always keep the bare links off them. The arm then leaves the padding and
inflation without reaching anything observed.

The seen voxels matter most after a guard stop: the arm brakes along its path into the margin
around what just blocked it, and the bare hand often ends inside the inflation, though a
padding away from every seen voxel. Judged on the inflated map, such starts stayed stuck.
"""

from __future__ import annotations

import numpy as np

from robonav.pipeline.collision.world import OCCUPANCY, CollisionWorld
from robonav.pipeline.planning.metrics import interpolate_path
from robonav.pipeline.types import FloatArray, StateValidFn


def escape_start(world: CollisionWorld, start: FloatArray, is_valid: StateValidFn,
                 rng: np.random.Generator, *, radius_rad: float, samples: int,
                 resolution_rad: float) -> FloatArray | None:
    """A valid state within `radius_rad` (every joint) of `start` that the arm can reach without
    its bare links touching the world, or None.

    Args:
        world: The planning world (its padding is what the start violates).
        start: (n,) start in collision with the padded robot [rad].
        is_valid: The planner's state check (limits, padded collisions, workspace).
        rng: Seeded generator for the samples.
        radius_rad: Largest move of any joint [rad]; 0 disables escaping.
        samples: Candidate states drawn; the closest usable one wins.
        resolution_rad: Check spacing along the way out [rad].

    Returns:
        (n,) escape state, or None when the start is not only inside the margin around the map
        (it touches itself or an object, or what the sensors saw; see the module docstring) or
        nothing near is free.
    """
    if radius_rad <= 0 or samples <= 0:
        return None
    pairs = world.collisions(start)
    if not pairs or any(other != OCCUPANCY for _, other in pairs):
        return None
    robot = world.robot
    low = np.maximum(start - radius_rad, robot.lower_limits_rad)
    high = np.minimum(start + radius_rad, robot.upper_limits_rad)
    candidates = rng.uniform(low, high, size=(samples, start.shape[0]))
    touches = way_out_touches(world, np.vstack([start, candidates]))
    if touches(start):
        return None
    # Closest first: the smallest move out of the padding is the one least likely to meet anything.
    order = np.argsort(np.max(np.abs(candidates - start), axis=1), kind="stable")
    for q in candidates[order]:
        if not is_valid(q):
            continue
        way = interpolate_path(np.vstack([start, q]), resolution_rad)
        if not any(touches(s) for s in way[1:-1]):
            return q
    return None


def way_out_touches(world: CollisionWorld, states: FloatArray) -> StateValidFn:
    """Whether a state on the way out touches what it must not (see the module docstring)."""
    seen = world.seen_voxels_m
    if seen is None:
        return lambda q: bool(world.collisions(q, padded=False))
    # Only voxels near the arm anywhere on the way out can be touched: box the link origins of
    # the start and every candidate, grown by the largest link and a margin for the small bulge
    # of joint-space segments between them.
    robot, voxel_m = world.robot, world.octree_resolution_m
    origins = np.concatenate([poses[:, :3, 3] for poses in robot.link_poses_batch(states).values()])
    reach_m = max(float(np.linalg.norm(v, axis=1).max()) for v in robot.link_hull_vertices.values())
    reach_m += world.padding_m + voxel_m + 0.05
    near = seen[np.all((seen >= origins.min(axis=0) - reach_m) & (seen <= origins.max(axis=0) + reach_m), axis=1)]

    def touches(q: FloatArray) -> bool:
        pairs = world.collisions(q, padded=False)
        return any(other != OCCUPANCY for _, other in pairs) or world.touches_cubes(q, near, voxel_m)
    return touches
