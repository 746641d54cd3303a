"""The exact re-check of the path a search returns, and what it need not check again.

`MotionPlanner` re-validates every path it returns: the shortcut leaves pieces of checked
segments unchecked, the search may have judged states by their spheres alone, and a request
may ask for a finer step than the edges'. A segment the shortcut's own check accepted in the
same query is known free at the edge resolution (the sphere-first check accepts only states
its spheres or FCL clear, so exactly too): `recording` notes such segments and
`path_rechecked` skips their states, all of them at the edge resolution and, at a finer one,
those both grids hold (`CollisionWorld.motion_valid(checked_rad=)`), so the re-check still
visits the states another check at that step (a benchmark's) visits.
"""

from __future__ import annotations

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.types import FloatArray, MotionValidFn


def segment_key(a: FloatArray, b: FloatArray) -> bytes:
    """A segment from `a` to `b`, by value and direction (the checked states are a + (b - a) * t)."""
    return a.tobytes() + b.tobytes()


def recording(motion_valid: MotionValidFn, checked: set[bytes]) -> MotionValidFn:
    """`motion_valid` that adds each segment it accepts to `checked` (`segment_key`)."""

    def check(a: FloatArray, b: FloatArray) -> bool:
        if motion_valid(a, b):
            checked.add(segment_key(a, b))
            return True
        return False

    return check


def path_rechecked(world: CollisionWorld, path: FloatArray, motion_valid: MotionValidFn, checked: set[bytes], *,
                   path_check_rad: float, edge_rad: float, own_check: bool) -> bool:
    """Every segment of `path` (K, dof) passes the exact check at `path_check_rad` (0: by
    `motion_valid` at the edge resolution `edge_rad`), skipping what `checked` vouches for.

    With a finer path check than the edges, the edge-resolution check is not repeated (the
    finer one is the stricter) unless `own_check` is False: the request's `motion_valid` adds
    workspace bounds to the planner's own check."""
    for a, b in zip(path[:-1], path[1:]):
        known = segment_key(a, b) in checked
        if path_check_rad <= 0:
            if not (known or motion_valid(a, b)):
                return False
        elif not world.motion_valid(a, b, path_check_rad, checked_rad=edge_rad if known else 0.0):
            return False
        elif not own_check and not known and not motion_valid(a, b):
            return False
    return True
