"""How far the robot is from the world: clearance of a state, of many states, of a path.

`CollisionWorld` mixes these in; they read its posed link shapes and its obstacles. Clearance is
measured on the bare (unpadded) link hulls and attached objects, against the scene objects and
the octree; self-distance is not included.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from robonav.pipeline.collision.edges import step_count
from robonav.pipeline.collision.fcl_shapes import sphere_box_distance
from robonav.pipeline.types import FloatArray

if TYPE_CHECKING:  # the world these methods run on
    from robonav.pipeline.collision.world import CollisionWorld


class ClearanceQueries:
    """Distance queries of `CollisionWorld`."""

    def clearance_m(self: CollisionWorld, q: FloatArray) -> float:
        """Smallest distance [m] from the UNPADDED robot hulls to the objects and octree at `q`.

        0 when touching or penetrating; +inf when the world is empty. Self-distance is not included.
        Against an octree this costs about 0.3-1 ms per link shape (FCL's distance traversal;
        ~10-20 ms for the Panda on a 50k-leaf map), so use it for metrics, not inside planning.
        """
        if self._broad_phase_usable():
            return self.min_clearance_m(np.asarray(q, dtype=np.float64).reshape(1, -1))
        centers = self._pose(q)
        best = math.inf
        if self._object_names:
            lower = sphere_box_distance(centers, self._radii, self._object_center, self._object_half)
            for flat in np.argsort(lower, axis=None):
                s, k = np.unravel_index(flat, lower.shape)
                if lower[s, k] >= best:
                    break
                best = min(best, self._distance(self._posed_obj(int(s), padded=False), self._object_fcl[int(k)]))
        if self._octree is not None:
            for s in range(len(self._links)):
                best = min(best, self._distance(self._posed_obj(s, padded=False), self._octree))
        if self._attached:
            best = min(best, self._attached_clearance_m(q))
        return best

    def min_clearance_m(self: CollisionWorld, states: FloatArray) -> float:
        """Smallest `clearance_m` over `states` (M, dof), M >= 1 [m].

        With the sphere model, every (state, link, obstacle) triple gets a lower bound from the
        link's spheres, and FCL measures triples in the order of their bound until the bound
        reaches the best distance found: the same answer from a few FCL distance queries (each
        ~0.1 ms on primitives, up to ~10 ms on a large octree) instead of one per near pair and
        state."""
        arr = self._path(states)
        if not self._broad_phase_usable():
            return min(self.clearance_m(q) for q in arr)
        bounds, poses = self._broad_phase.clearance_pair_bounds_m(arr)
        obstacles = [*self._object_fcl, self._octree]
        best, posed = math.inf, -1
        # The triples in the order of their bound, each taken by argmin: the loop ends after a
        # few, and sorting all of them (a thousand and more) cost more than the FCL queries.
        open_bounds = bounds.reshape(-1).copy()
        while True:
            flat = int(np.argmin(open_bounds))  # the first of equal bounds, as a stable sort
            if open_bounds[flat] >= best or best <= 0.0:
                break
            open_bounds[flat] = math.inf
            m, link, k = np.unravel_index(flat, bounds.shape)
            if m != posed:
                self._set_link_poses(poses[m])
                posed = m
            for s in self._shapes_of_link[link]:
                best = min(best, self._distance(self._posed_obj(s, padded=False), obstacles[k]))
        return best

    def _attached_clearance_m(self: CollisionWorld, q: FloatArray) -> float:
        """Smallest distance [m] from the unpadded attached objects to the objects and octree; needs `_pose(q)` first."""
        best = math.inf
        for attached, _, _ in self._attached.pose(q, self._world_from_shape_link):
            for other in (*self._object_fcl, *([self._octree] if self._octree is not None else [])):
                best = min(best, self._distance(attached.obj, other))
        return best

    def path_clearance_m(self: CollisionWorld, path: FloatArray, resolution_rad: float) -> float:
        """Smallest `clearance_m` over `path` (K, dof) sampled at most `resolution_rad` apart [m]."""
        arr = self._path(path)
        states = [arr[0]]
        for i in range(arr.shape[0] - 1):
            steps = step_count(arr[i], arr[i + 1], resolution_rad)
            states += [arr[i] + (arr[i + 1] - arr[i]) * (k / steps) for k in range(1, steps + 1)]
        return self.min_clearance_m(np.array(states))
