"""Leaving a start that is inside the robot's padding around the occupancy map.

An arm that braked in front of a newly seen obstacle, or whose map grew by a few noisy voxels,
often rests with a padded link just inside the inflated map. It touches nothing, but every plan
from there is START_IN_COLLISION and the arm is stuck. MoveIt's planning pipeline handles this
with its FixStartStateCollision adapter: it samples states near the start ("jiggles", by default
within 2 % of each joint range, up to 100 samples), plans from the first valid one and puts the
real start in front of the path, without checking that first segment.

This does the same with one rule more, so that the way out is still collision-checked: only
occupancy pairs may be in collision at the start, the bare (unpadded) links must not touch the
map or any object there, and every state of the straight segment to the escape state must keep
the bare links clear too. The arm then leaves the padding without ever reaching what the map
says is occupied (the map is already inflated around what the cameras saw).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from robonav.pipeline.collision import OCCUPANCY, CollisionWorld
from robonav.pipeline.planning.metrics import interpolate_path
from robonav.pipeline.transforms import FloatArray


def escape_start(world: CollisionWorld, start: FloatArray, is_valid: Callable[[FloatArray], bool],
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
        (n,) escape state, or None when the start is not only inside the padding around the
        map (it touches itself, an object or the map with bare links) or nothing near is free.
    """
    if radius_rad <= 0 or samples <= 0:
        return None
    pairs = world.collisions(start)
    if not pairs or any(other != OCCUPANCY for _, other in pairs) or world.collisions(start, padded=False):
        return None
    robot = world.robot
    low = np.maximum(start - radius_rad, robot.lower_limits_rad)
    high = np.minimum(start + radius_rad, robot.upper_limits_rad)
    candidates = rng.uniform(low, high, size=(samples, start.shape[0]))
    # Closest first: the smallest move out of the padding is the one least likely to meet anything.
    order = np.argsort(np.max(np.abs(candidates - start), axis=1), kind="stable")
    for q in candidates[order]:
        if not is_valid(q):
            continue
        way = interpolate_path(np.vstack([start, q]), resolution_rad)
        if not any(world.collisions(s, padded=False) for s in way[1:-1]):
            return q
    return None
