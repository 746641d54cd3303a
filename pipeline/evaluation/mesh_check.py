"""Exact-geometry collision check of a robot: link MESHES (FCL BVH models) against primitives and itself.

`CollisionWorld` (collision.py) plans with convex hulls of the links, optionally padded: fast,
and conservative by construction. This module is the independent referee for benchmarks: it
checks the triangle meshes themselves (`fcl.BVHModel`, no hulls, no padding), the way
MotionBenchMaker's own FCL/MoveIt checks and the peers' published re-checks do, so a path that
passes here is collision-free on the model the benchmark was made with.

It is deliberately simple (a bounding-sphere prefilter, then FCL per pair) and slower per state
than `CollisionWorld`; it is meant for re-checking returned paths, not for planning.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import fcl
import numpy as np

from robonav.pipeline.collision.fcl_shapes import link_shape_geometry
from robonav.pipeline.planning.metrics import as_path, interpolate_path
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.types import FloatArray

FINE_STEP_RAD = 0.01
"""Default largest single-joint change between re-checked states [rad]."""


@dataclass(frozen=True)
class PathCheck:
    """Verdict of `MeshCollisionChecker.check_path`.

    Attributes:
        valid: True when the path has the right ends, stays within the joint limits and every
            interpolated state is collision-free.
        states_checked: Number of interpolated states whose collisions were checked.
        first_invalid_state: Index into the interpolated path of the first colliding state,
            or None.
        pairs: Colliding pairs at that state: (link, object name) or (link, link).
        detail: Human-readable reason when not valid; 'ok' otherwise.
    """

    valid: bool
    states_checked: int
    first_invalid_state: int | None
    pairs: tuple[tuple[str, str], ...]
    detail: str


class MeshCollisionChecker:
    """A robot's link meshes against primitive obstacles and against each other, in the world frame.

    Self-collision skips adjacent links (`RobotModel.adjacent_link_pairs`) and the config's
    `allowed_collision_pairs`, as `CollisionWorld` does. Not thread-safe (FCL objects are
    re-posed per query, and `RobotModel` FK shares a buffer).
    """

    def __init__(self, robot: RobotModel, objects: Sequence[SceneObject] = ()) -> None:
        """Build one BVH (or primitive) FCL object per link shape.

        Args:
            robot: Kinematics and link geometry; mesh shapes must carry their triangles.
            objects: Initial obstacles, posed in the world frame.
        """
        self._robot = robot
        self._shape_links: list[str] = []
        self._shape_link_index: list[int] = []
        self._link_from_shape: list[FloatArray] = []
        self._shape_objs: list[fcl.CollisionObject] = []
        centers, radii = [], []
        for link_index, (link, shapes) in enumerate(robot.link_collision_shapes.items()):
            for shape in shapes:
                geometry, center_shape, radius = link_shape_geometry(shape)
                self._shape_links.append(link)
                self._shape_link_index.append(link_index)
                self._link_from_shape.append(shape.link_from_shape)
                self._shape_objs.append(fcl.CollisionObject(geometry, fcl.Transform()))
                centers.append(center_shape)
                radii.append(radius)
        self._link_from_shape_stack = np.array(self._link_from_shape, dtype=np.float64).reshape(-1, 4, 4)
        self._centers_shape = np.array(centers, dtype=np.float64).reshape(-1, 3)
        self._radii = np.array(radii, dtype=np.float64)
        ignored = set(robot.adjacent_link_pairs) | {tuple(sorted(p)) for p in robot.config.allowed_collision_pairs}
        n = len(self._shape_links)
        self._self_pairs = [
            (i, j) for i in range(n) for j in range(i + 1, n)
            if self._shape_links[i] != self._shape_links[j]
            and tuple(sorted((self._shape_links[i], self._shape_links[j]))) not in ignored
        ]
        self._request = fcl.CollisionRequest()
        self._object_names: list[str] = []
        self._object_fcl: list[fcl.CollisionObject] = []
        self._object_center = np.zeros((0, 3))
        self._object_half = np.zeros((0, 3))
        self.set_objects(objects)

    @property
    def robot(self) -> RobotModel:
        return self._robot

    @property
    def self_collision_pairs(self) -> list[tuple[str, str]]:
        """Link pairs checked for self-collision (adjacent and allowed pairs excluded)."""
        return sorted({(self._shape_links[i], self._shape_links[j]) for i, j in self._self_pairs})

    def set_objects(self, objects: Sequence[SceneObject]) -> None:
        """Replace the obstacles (poses in the world frame; capsule length between cap centers).

        Raises:
            ValueError: two objects share a name.
        """
        names = [o.name for o in objects]
        for i, name in enumerate(names):
            if name in names[:i]:
                raise ValueError(f"objects[{i}] name '{name}' is duplicated")
        fcl_objs, centers, halves = [], [], []
        for obj in objects:
            pose = obj.world_from_object
            geometry, half = _object_geometry(obj)
            fcl_objs.append(fcl.CollisionObject(geometry, fcl.Transform(pose[:3, :3], pose[:3, 3])))
            centers.append(pose[:3, 3])
            halves.append(np.abs(pose[:3, :3]) @ half)  # world AABB of the object's local bounding box
        self._object_names, self._object_fcl = names, fcl_objs
        self._object_center = np.array(centers, dtype=np.float64).reshape(-1, 3)
        self._object_half = np.array(halves, dtype=np.float64).reshape(-1, 3)

    def collisions(self, q: FloatArray, *, first_only: bool = False) -> list[tuple[str, str]]:
        """Colliding pairs at `q` (dof,): (link, object name) first, then (link, link).

        Touching counts as colliding (FCL reports contact at zero distance).
        """
        link_poses = self._robot.link_pose_stack(q)
        world_from_shape = link_poses[self._shape_link_index] @ self._link_from_shape_stack
        centers = np.einsum("sij,sj->si", world_from_shape[:, :3, :3], self._centers_shape) + world_from_shape[:, :3, 3]
        posed = [False] * len(self._shape_objs)

        def obj(s: int) -> fcl.CollisionObject:
            if not posed[s]:
                self._shape_objs[s].setRotation(world_from_shape[s, :3, :3])
                self._shape_objs[s].setTranslation(world_from_shape[s, :3, 3])
                posed[s] = True
            return self._shape_objs[s]

        hits: list[tuple[str, str]] = []
        if self._object_names:
            # Bounding sphere vs the object's world AABB: only pairs that might touch reach FCL.
            gap = np.maximum(np.abs(centers[:, None, :] - self._object_center[None]) - self._object_half[None], 0.0)
            near = np.einsum("skj,skj->sk", gap, gap) <= (self._radii ** 2)[:, None]
            for s, k in zip(*np.nonzero(near)):
                pair = (self._shape_links[s], self._object_names[k])
                if pair not in hits and self._collide(obj(int(s)), self._object_fcl[k]):
                    hits.append(pair)
                    if first_only:
                        return hits
        for a, b in self._self_pairs:
            pair = (self._shape_links[a], self._shape_links[b])
            if pair in hits or np.sum((centers[a] - centers[b]) ** 2) > (self._radii[a] + self._radii[b]) ** 2:
                continue
            if self._collide(obj(a), obj(b)):
                hits.append(pair)
                if first_only:
                    return hits
        return hits

    def in_collision(self, q: FloatArray) -> bool:
        """True when any link mesh at `q` (dof,) touches an obstacle or a non-ignored link."""
        return bool(self.collisions(q, first_only=True))

    def check_path(
        self,
        path: FloatArray,
        *,
        start_rad: FloatArray | None = None,
        goal_rad: FloatArray | None = None,
        max_step_rad: float = FINE_STEP_RAD,
        endpoint_tolerance_rad: float = 1e-6,
    ) -> PathCheck:
        """Check a joint-space path finely: ends, joint limits and every interpolated state.

        Args:
            path: (K, dof) waypoints [rad], K >= 1.
            start_rad: (dof,) required first waypoint, or None to skip that check [rad].
            goal_rad: (dof,) required last waypoint, or None to skip that check [rad].
            max_step_rad: Largest single-joint change between checked states [rad]; every
                segment is split evenly (`metrics.interpolate_path`).
            endpoint_tolerance_rad: Largest per-joint distance of the ends from start/goal [rad].

        Returns:
            The verdict; collisions are looked for only when ends and limits are fine.

        Raises:
            ValueError: `path` is not (K, dof) with finite entries.
        """
        arr = as_path(path)
        if arr.shape[1] != self._robot.dof:
            raise ValueError(f"path must have shape (K, {self._robot.dof}), got shape {arr.shape}")
        for label, want, row in (("start", start_rad, arr[0]), ("goal", goal_rad, arr[-1])):
            if want is None:
                continue
            error = float(np.max(np.abs(row - self._robot.validate_q(want, f"{label}_rad"))))
            if error > endpoint_tolerance_rad:
                return PathCheck(False, 0, None, (), f"path does not {'start at the start' if label == 'start' else 'end at the goal'} "
                                                     f"(largest joint difference {error:.3g} rad)")
        for i, q in enumerate(arr):
            violations = self._robot.check_joint_limits(q)
            if violations:
                return PathCheck(False, 0, None, (), f"waypoint {i} is outside the joint limits: {'; '.join(violations)}")
        dense = interpolate_path(arr, max_step_rad)
        for i, q in enumerate(dense):
            pairs = self.collisions(q, first_only=True)
            if pairs:
                named = ", ".join(f"{a}|{b}" for a, b in pairs)
                return PathCheck(False, i + 1, i, tuple(pairs),
                                 f"interpolated state {i} of {len(dense)} is in collision: {named}")
        return PathCheck(True, len(dense), None, (), "ok")

    def _collide(self, a: fcl.CollisionObject, b: fcl.CollisionObject) -> bool:
        return fcl.collide(a, b, self._request, fcl.CollisionResult()) > 0


def _object_geometry(obj: SceneObject) -> tuple[fcl.CollisionGeometry, FloatArray]:
    """FCL geometry of a scene object and the half extents (3,) of its local bounding box [m]."""
    if obj.type == "box":
        return fcl.Box(*obj.size_m), 0.5 * np.array(obj.size_m, dtype=np.float64)  # type: ignore[misc]
    radius = float(obj.radius_m)  # type: ignore[arg-type]
    if obj.type == "cylinder":
        return fcl.Cylinder(radius, obj.length_m), np.array([radius, radius, 0.5 * obj.length_m])  # type: ignore[operator]
    if obj.type == "sphere":
        return fcl.Sphere(radius), np.full(3, radius)
    return fcl.Capsule(radius, obj.length_m), np.array([radius, radius, 0.5 * obj.length_m + radius])  # type: ignore[operator]
