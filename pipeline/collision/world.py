"""Collision checking of a robot against itself, primitive scene objects and an occupancy octree (FCL).

Every robot shape is an `fcl.Convex` of its convex hull (GJK on a hull is much faster than on
the triangle mesh). A hull contains its mesh, so this is conservative: it can report contact in
a concave pocket of a link where the mesh itself is free; a contact of hulls is therefore confirmed
on the exact shapes (`fcl_shapes.ExactLinkShapes`). Robot-vs-world checks use hulls grown by
`padding_m` (see `link_geometry.grow_hull`); self-collision and clearance use the ungrown hulls.

Each check first rejects pairs whose bounding spheres cannot touch (numpy), then runs FCL per
pair in Python. Against FCL's DynamicAABBTree managers (Panda, 6 boxes and a 53k-leaf octree)
this measured 140 vs 165 us on random states and 210 vs 178 us on free ones: a wash, so the
simpler per-pair form won; it also names the colliding objects, which python-fcl's manager
callbacks cannot (they receive anonymous copies of the objects).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import fcl
import numpy as np
import numpy.typing as npt

from robonav.pipeline.collision.attached import AttachedChecks, AttachedObject, Attachments
from robonav.pipeline.collision.clearance import ClearanceQueries
from robonav.pipeline.collision.edges import bisection_order, step_count
from robonav.pipeline.collision.fcl_shapes import (
    OCCUPANCY,
    ExactLinkShapes,
    convex_shape,
    object_geometry,
    occupied_leaf_centers,
    octree_object,
    world_aabb,
)
from robonav.pipeline.collision.sphere_first import SphereFirstChecks
from robonav.pipeline.collision.spheres.broad_phase import SphereBroadPhase
from robonav.pipeline.collision.surface_allowance import SurfaceAllowance
from robonav.pipeline.robot.link_geometry import grow_hull
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.types import FloatArray


class CollisionWorld(ClearanceQueries, SphereFirstChecks, SurfaceAllowance, AttachedChecks):
    """A robot model plus the obstacles it must avoid, all in the world frame.

    Not thread-safe: FCL objects are re-posed on every query. Mixed in: the distance queries
    (`clearance.py`), the sphere-first checks (`sphere_first.py`), the map's clearance and its
    allowance near a query's ends (`surface_allowance.py`), the attached objects' checks (`attached.py`).
    """

    def __init__(self, robot: RobotModel, padding_m: float | None = None, *, broad_phase: bool = True) -> None:
        """Build the robot's FCL shapes; the world starts empty.

        Args:
            robot: Kinematics and link geometry.
            padding_m: Robot-vs-world safety margin [m]; None takes `robot.config.padding_m`.
            broad_phase: Clear states with the compiled sphere broad phase before FCL
                (`in_collision`, `motion_valid`, `path_valid`; same answers, ~10-30x faster on
                free states). False checks every state with FCL alone (for A/B comparisons).
        """
        padding = robot.config.padding_m if padding_m is None else float(padding_m)
        if not (math.isfinite(padding) and padding >= 0):
            raise ValueError(f"padding_m must be finite and >= 0, got {padding_m}")
        self._robot = robot
        self._padding_m = padding
        self._links: list[str] = []
        self._link_of_shape: list[int] = []
        self._objs: list[fcl.CollisionObject] = []
        self._padded_objs: list[fcl.CollisionObject] = []
        centers, radii, padded_radii = [], [], []
        for link, shapes in robot.link_collision_shapes.items():
            for shape in shapes:
                vertices, triangles = shape.hull_vertices, shape.hull_triangles
                grown_v, grown_t = grow_hull(vertices, triangles, padding) if padding > 0 else (vertices, triangles)
                center = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
                self._links.append(link)
                self._link_of_shape.append(robot.collision_link_names.index(link))
                self._objs.append(fcl.CollisionObject(convex_shape(vertices, triangles), fcl.Transform()))
                self._padded_objs.append(fcl.CollisionObject(convex_shape(grown_v, grown_t), fcl.Transform()))
                centers.append(center)
                radii.append(float(np.max(np.linalg.norm(vertices - center, axis=1))))
                padded_radii.append(float(np.max(np.linalg.norm(grown_v - center, axis=1))))
        self._centers_link = np.array(centers, dtype=np.float64).reshape(-1, 3)
        self._radii = np.array(radii, dtype=np.float64)
        self._padded_radii_sq = np.array(padded_radii, dtype=np.float64)[:, None] ** 2
        self._shape_link_index = np.array(self._link_of_shape, dtype=np.int64)
        self._one_shape_per_link = self._link_of_shape == list(range(len(robot.collision_link_names)))
        ignored = set(robot.adjacent_link_pairs) | {tuple(sorted(p)) for p in robot.config.allowed_collision_pairs}
        n = len(self._links)
        self._self_pairs = np.array(
            [(i, j) for i in range(n) for j in range(i + 1, n)
             if self._links[i] != self._links[j] and tuple(sorted((self._links[i], self._links[j]))) not in ignored],
            dtype=np.int64,
        ).reshape(-1, 2)
        self._request = fcl.CollisionRequest()
        self._exact = ExactLinkShapes([s for link in robot.collision_link_names for s in robot.link_collision_shapes[link]])
        self._distance_request = fcl.DistanceRequest()
        self._octree: fcl.CollisionObject | None = None
        self._seen_voxels_m: FloatArray | None = None
        self._octree_resolution_m = 0.0
        self._init_allowance(robot.dof)
        self._object_names: list[str] = []
        self._object_fcl: list[fcl.CollisionObject] = []
        self._object_center = np.zeros((0, 3))
        self._object_half = np.zeros((0, 3))
        self._posed: list[int] = [0] * n
        self._posed_padded: list[int] = [0] * n
        self._generation = 0
        self._revision = 0
        self._world_from_shape_link = np.zeros((n, 4, 4))
        self._attached = Attachments(robot, self._links, padding)
        self._shapes_of_link = [[s for s, li in enumerate(self._link_of_shape) if li == link]
                                for link in range(len(robot.collision_link_names))]
        link_pairs = {pair: p for p, pair in enumerate(self.self_collision_pairs)}
        self._self_pair_link_pair = np.array([link_pairs[(self._links[a], self._links[b])] for a, b in self._self_pairs],
                                             dtype=np.int64)
        # Conservative: a state it clears is FCL-free, so only its suspects reach `_check`.
        self._broad_phase = (SphereBroadPhase(robot, padding_m=padding, self_pairs=self.self_collision_pairs)
                             if broad_phase else None)

    @property
    def robot(self) -> RobotModel:
        return self._robot

    @property
    def revision(self) -> int:
        """Counts changes of the world (objects, octree, attached objects); caches key on it."""
        return self._revision

    @property
    def padding_m(self) -> float:
        return self._padding_m

    @property
    def self_collision_pairs(self) -> list[tuple[str, str]]:
        """Link pairs checked for self-collision (adjacent and allowed pairs excluded)."""
        return sorted({(self._links[i], self._links[j]) for i, j in self._self_pairs})

    @property
    def has_octree(self) -> bool:
        return self._octree is not None

    @property
    def object_names(self) -> tuple[str, ...]:
        return tuple(self._object_names)

    def set_octree(self, octomap_binary: bytes, resolution_m: float,
                   seen_voxels_m: npt.ArrayLike | None = None, *, clearance_m: float | None = None,
                   surface_m: npt.ArrayLike | None = None, surface_resolution_m: float | None = None) -> None:
        """Replace the occupancy map with an octree in the world frame.

        Args:
            octomap_binary: What `octomap.OcTree.writeBinary()` returns (header and data).
            resolution_m: Leaf size [m]; must match the `res` line of the header.
            seen_voxels_m: (N, 3) centers of the voxels the sensors saw, when the octree is
                those grown by an inflation (`Occupancy.occupied_centers_m`) [m]; None: unknown.
            clearance_m: The inflation the octree was grown by [m]. With `seen_voxels_m`, the
                broad phase keeps the padded links this far off the seen voxels, and near the
                anchors of a query the map's clearance is released (`surface_allowance.py`).
                None: the octree is the map, as it is.
            surface_m: (M, 3) seen points (or cells of a grid finer than the map's) the links
                must keep off near the anchors [m]; None: the seen voxels. Needs `clearance_m`.
            surface_resolution_m: Cell size of `surface_m` (<= `resolution_m`) [m].
        """
        self._revision += 1
        if not (math.isfinite(resolution_m) and resolution_m > 0):
            raise ValueError(f"resolution_m must be finite and > 0, got {resolution_m}")
        seen = None if seen_voxels_m is None else np.asarray(seen_voxels_m, dtype=np.float64)
        if seen is not None and (seen.ndim != 2 or seen.shape[1] != 3 or not np.all(np.isfinite(seen))):
            raise ValueError(f"seen_voxels_m must be a finite (N, 3) array, got shape {seen.shape}")
        if clearance_m is not None and not (math.isfinite(clearance_m) and clearance_m >= 0):
            raise ValueError(f"clearance_m must be finite and >= 0, got {clearance_m}")
        if (surface_m is not None or clearance_m is not None) and seen is None:
            raise ValueError("clearance_m and surface_m need seen_voxels_m")
        octree = octree_object(octomap_binary, resolution_m)
        # Only a map that passed the checks above replaces the seen voxels of the last one.
        self._seen_voxels_m = seen
        self._octree_resolution_m = float(resolution_m)
        self._octree = octree
        self._reset_allowance()
        if octree is None:
            if self._broad_phase is not None:
                self._broad_phase.clear_occupancy()
            return
        if clearance_m is not None and seen is not None and seen.shape[0]:
            surface = None if surface_m is None else np.asarray(surface_m, dtype=np.float64)
            self._set_map_layers(seen, float(resolution_m), float(clearance_m), surface, surface_resolution_m)
        elif self._broad_phase is not None:
            self._broad_phase.set_occupied_voxels(occupied_leaf_centers(octomap_binary, resolution_m), resolution_m)

    @property
    def seen_voxels_m(self) -> FloatArray | None:
        """(N, 3) centers of the map's voxels before inflation, side `octree_resolution_m` [m];
        None when the map came without them (or there is no map)."""
        return self._seen_voxels_m

    @property
    def octree_resolution_m(self) -> float:
        """Leaf size of the current map [m]; 0 without one."""
        return self._octree_resolution_m

    def build_exact_shapes(self) -> None:
        """Build the exact link geometry contacts are confirmed on (`ExactLinkShapes.build`) now,
        for a service's warm-up; otherwise each shape is built at its link's first contact."""
        self._exact.build()

    def clear_octree(self) -> None:
        self._revision += 1
        self._octree = None
        self._seen_voxels_m = None
        self._octree_resolution_m = 0.0
        self._reset_allowance()
        if self._broad_phase is not None:
            self._broad_phase.clear_occupancy()

    def set_objects(self, objects: Sequence[SceneObject]) -> None:
        """Replace the primitive obstacles (poses in the world frame; capsule length between cap centers)."""
        self._revision += 1
        names = [o.name for o in objects]
        for i, name in enumerate(names):
            if name == OCCUPANCY or name in names[:i] or name in self._attached:
                raise ValueError(f"objects[{i}] name '{name}' is reserved, duplicated or an attached object's")
        fcl_objs, centers, halves = [], [], []
        for obj in objects:
            pose = obj.world_from_object
            fcl_objs.append(fcl.CollisionObject(object_geometry(obj), fcl.Transform(pose[:3, :3], pose[:3, 3])))
            center, half = world_aabb(obj, pose)
            centers.append(center)
            halves.append(half)
        self._object_names, self._object_fcl = names, fcl_objs
        self._exact.set_objects(objects, self._padding_m)
        self._object_center = np.array(centers).reshape(-1, 3)
        self._object_half = np.array(halves).reshape(-1, 3)
        if self._broad_phase is not None:
            self._broad_phase.set_objects(objects)

    def clear_objects(self) -> None:
        self._revision += 1
        self.set_objects([])

    @property
    def attached_objects(self) -> tuple[AttachedObject, ...]:
        """The objects fixed to robot links, in attach order."""
        return self._attached.infos

    def attach_object(
        self,
        obj: SceneObject,
        link: str,
        touch_links: Sequence[str] = (),
        *,
        q: FloatArray | None = None,
        world_from_link: FloatArray | None = None,
    ) -> AttachedObject:
        """Fix `obj` to the robot frame `link`; from then on it moves with that link in every check.

        The object collides with the world (objects and octree, padded like the links except
        meshes), with every robot link other than `link` and `touch_links` (unpadded, like
        self-collision) and with objects attached to other links. Attaching a name that is
        already attached replaces it.

        Args:
            obj: The object, posed in the world frame at the moment given by `q` or `world_from_link`.
            link: A frame of the robot (a link with or without collision geometry).
            touch_links: Robot links the object may touch, e.g. the fingers that hold it.
            q: (dof,) configuration at which `obj` has its world pose [rad].
            world_from_link: (4, 4) pose of `link` at that moment instead of `q`. `np.eye(4)`
                means `obj`'s pose already is link_from_object.

        Returns:
            The attachment, holding link_from_object (4, 4).

        Raises:
            ValueError: the name is a world object's or reserved, `link` or a touch link is not a
                frame of the robot, or not exactly one of `q` and `world_from_link` is given.
        """
        self._revision += 1
        if obj.name == OCCUPANCY or obj.name in self._object_names:
            raise ValueError(f"object name '{obj.name}' is reserved or names a world object; remove it from the world first")
        return self._attached.attach(obj, link, touch_links, q=q, world_from_link=world_from_link)

    def detach_object(self, name: str, *, q: FloatArray | None = None) -> SceneObject | None:
        """Unfix an attached object.

        Args:
            name: The attached object's name.
            q: (dof,) configuration [rad]; when given, the object posed in the world frame at `q`
                is returned (MoveIt's detach keeps it where the robot left it).

        Returns:
            The object posed in the world at `q`, or None when `q` is None.

        Raises:
            ValueError: no attached object has this name.
        """
        self._revision += 1
        return self._attached.detach(name, q=q)

    def attached_world_from_object(self, name: str, q: FloatArray) -> FloatArray:
        """(4, 4) world pose of the attached object `name` with the robot at `q` (dof,)."""
        return self._attached.world_from_object(name, q)

    def link_pairs_in_collision(self, q: FloatArray, pairs: Sequence[tuple[str, str]]) -> list[tuple[str, str]]:
        """Which of the link `pairs` touch at `q` (dof,), on the UNPADDED hulls.

        Ignores adjacency and `allowed_collision_pairs`: this is the raw test the
        allowed-collision matrix is generated from (`acm.py`). Attached objects are not included.
        """
        shape_pairs = []  # (shape a, shape b, index into pairs)
        for p, (link_a, link_b) in enumerate(pairs):
            shapes_a = [s for s, lk in enumerate(self._links) if lk == link_a]
            shapes_b = [s for s, lk in enumerate(self._links) if lk == link_b]
            if not shapes_a or not shapes_b:
                raise ValueError(f"pair ({link_a}, {link_b}) names a link without checked collision geometry")
            shape_pairs += [(a, b, p) for a in shapes_a for b in shapes_b]
        table = np.array(shape_pairs, dtype=np.int64).reshape(-1, 3)
        centers = self._pose(q)
        offsets = centers[table[:, 0]] - centers[table[:, 1]]
        near = np.einsum("pi,pi->p", offsets, offsets) <= (self._radii[table[:, 0]] + self._radii[table[:, 1]]) ** 2
        hit = np.zeros(len(pairs), dtype=bool)
        for a, b, p in table[near]:
            if not hit[p]:
                hit[p] = self._collide(self._posed_obj(int(a), padded=False), self._posed_obj(int(b), padded=False))
        return [tuple(pairs[p]) for p in np.flatnonzero(hit)]

    def in_collision(self, q: FloatArray) -> bool:
        """True when the robot at `q` (dof,) touches itself, an object or the octree (padded vs the world)."""
        return bool(self._map_aware_check(self._robot.validate_q(q), first_only=True))

    def _broad_phase_usable(self) -> bool:
        # Attached objects are not in the sphere model yet: fall back to FCL for every state.
        return self._broad_phase is not None and not self._attached

    def collisions(self, q: FloatArray, *, padded: bool = True) -> list[tuple[str, str]]:
        """Every colliding pair at `q`: (link, link), (link, object name) or (link, 'occupancy').

        Pairs with an attached object name it first: (attached, link), (attached, object),
        (attached, 'occupancy') or (attached, other attached object). `padded=False` checks the
        bare links against the world too (attached objects stay padded), e.g. to tell a state
        inside the padding from one touching an obstacle.
        """
        return self._map_aware_check(self._robot.validate_q(q), first_only=False, padded=padded)

    def motion_valid(self, q_a: FloatArray, q_b: FloatArray, resolution_rad: float, *,
                     checked_rad: float = 0.0) -> bool:
        """True when every state on the straight joint-space segment from `q_a` to `q_b` is free.

        States are spaced at most `resolution_rad` apart in every joint; both ends are checked.
        The end `q_b` is checked first, then the interior in bisection order, then `q_a`, so a
        blocked edge is usually rejected after a few states.

        With `checked_rad` > 0 the caller vouches that the segment passed this check, or a
        stricter one, at that step: the states the two checks share are not checked again
        (`SphereBroadPhase.edge_suspects`).
        """
        a = self._robot.validate_q(q_a, "q_a")
        b = self._robot.validate_q(q_b, "q_b")
        if not 0 <= checked_rad < math.inf:  # NaN fails too
            raise ValueError(f"checked_rad must be finite and >= 0, got {checked_rad}")
        if self._broad_phase_usable():
            return self._suspects_free(a, b, resolution_rad, lambda _q: True, checked_rad)
        steps = step_count(a, b, resolution_rad)
        every = steps // math.gcd(steps, step_count(a, b, checked_rad)) if checked_rad > 0 else 0
        for k in (steps, *bisection_order(steps), 0):
            if every and k % every == 0:
                continue
            q = b if k == steps else a if k == 0 else a + (b - a) * (k / steps)
            if self._map_aware_check(q, first_only=True):
                return False
        return True

    def path_valid(self, path: FloatArray, resolution_rad: float) -> bool:
        """True when every segment of `path` (K, dof), K >= 1, passes `motion_valid`."""
        arr = self._path(path)
        if arr.shape[0] == 1:
            return not self.in_collision(arr[0])
        return all(self.motion_valid(arr[i], arr[i + 1], resolution_rad) for i in range(arr.shape[0] - 1))

    def _path(self, path: FloatArray) -> FloatArray:
        arr = np.asarray(path, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[0] < 1 or arr.shape[1] != self._robot.dof:
            raise ValueError(f"path must have shape (K >= 1, {self._robot.dof}), got shape {arr.shape}")
        for i in range(arr.shape[0]):
            self._robot.validate_q(arr[i], f"path[{i}]")
        return arr

    def _pose(self, q: FloatArray) -> FloatArray:
        """Runs FK for `q`; FCL objects are then posed lazily. Returns shape centers (S, 3), world frame."""
        # The broad phase's compiled kinematics (read from the same Pinocchio model) cost less
        # than half of a Pinocchio round trip, and every FCL check starts here.
        poses = (self._robot.link_pose_stack(q) if self._broad_phase is None
                 else self._broad_phase.link_pose_stack(self._robot.validate_q(q)))
        self._set_link_poses(poses)
        return np.einsum("sij,sj->si", self._world_from_shape_link[:, :3, :3], self._centers_link) \
            + self._world_from_shape_link[:, :3, 3]

    def _set_link_poses(self, poses: FloatArray) -> None:
        """world_from_link (L, 4, 4) of the collision links become the poses FCL objects take."""
        if not self._one_shape_per_link:
            poses = poses[self._shape_link_index]
        self._world_from_shape_link = poses
        self._generation += 1

    def _posed_obj(self, s: int, *, padded: bool) -> fcl.CollisionObject:
        # Re-posing costs a few microseconds per object, so only objects that reach FCL get it.
        objs, stamp = (self._padded_objs, self._posed_padded) if padded else (self._objs, self._posed)
        obj = objs[s]
        if stamp[s] != self._generation:
            pose = self._world_from_shape_link[s]
            obj.setRotation(pose[:3, :3])
            obj.setTranslation(pose[:3, 3])
            stamp[s] = self._generation
        return obj

    def _collide(self, a: fcl.CollisionObject, b: fcl.CollisionObject) -> bool:
        return fcl.collide(a, b, self._request, fcl.CollisionResult()) > 0

    def _distance(self, a: fcl.CollisionObject, b: fcl.CollisionObject) -> float:
        d = fcl.distance(a, b, self._distance_request, fcl.DistanceResult())
        # FCL returns -1 for penetration and DBL_MAX for an octree without occupied cells.
        return 0.0 if d <= 0 else (math.inf if d >= 1e300 else float(d))

    def _check(self, q: FloatArray, *, first_only: bool, padded: bool = True,
               tier: int = -1) -> list[tuple[str, str]]:
        """FCL on the pairs the spheres of clearance `tier` flag; tier 0 checks the map's surface
        instead of its inflated octree (`surface_allowance.py`)."""
        near_objects, near_octree, near_self, centers = self._near_pairs(q, tier)
        octree = self._surface_octree if tier == 0 and self._surface_octree is not None else self._octree
        hits: list[tuple[str, str]] = []
        links, poses, exact = self._links, self._world_from_shape_link, self._exact
        # A hull's contact is confirmed on the link's exact shape (`ExactLinkShapes`).
        grown = padded and self._padding_m > 0
        if near_objects is not None:
            exact_objects = exact.padded_objects if grown else self._object_fcl
            for s, k in zip(*np.nonzero(near_objects)):
                pair = (links[s], self._object_names[k])
                if pair not in hits and self._collide(self._posed_obj(int(s), padded=padded), self._object_fcl[k]) \
                        and exact.collide_with(int(s), poses[s], exact_objects[k]):
                    hits.append(pair)
                    if first_only:
                        return hits
        if octree is not None:
            for s in np.flatnonzero(near_octree):
                pair = (links[s], OCCUPANCY)
                if pair not in hits and self._collide(self._posed_obj(int(s), padded=padded), octree) \
                        and exact.collide_with(int(s), poses[s], None if grown else octree):
                    hits.append(pair)
                    if first_only:
                        return hits
        for a, b in self._self_pairs[near_self]:
            pair = (links[a], links[b])
            if pair in hits:
                continue
            if self._collide(self._posed_obj(int(a), padded=False), self._posed_obj(int(b), padded=False)) \
                    and exact.collide(int(a), int(b), poses[a], poses[b]):
                hits.append(pair)
                if first_only:
                    return hits
        if self._attached:
            self._check_attached(q, centers, hits, first_only=first_only)
        return hits

    def _near_pairs(self, q: FloatArray, tier: int = -1):  # noqa: ANN202 - four arrays
        """Pose the robot at `q` and say which pairs FCL must test.

        Returns (S, K) shape-object and (S,) shape-octree masks, a mask over `_self_pairs` (the
        object mask is None without objects) and the shapes' centers (S, 3), or None for them
        when the sphere model answered: then only pairs whose spheres touch are tested (the
        spheres contain the padded hulls, so no other pair can collide), which saves most FCL
        calls and the culling here; otherwise bounding spheres against the objects' boxes cull."""
        if self._broad_phase_usable():
            objects, voxels, pairs, poses = self._broad_phase.suspect_pairs(self._robot.validate_q(q), tier=tier)
            self._set_link_poses(poses.copy())
            link = self._shape_link_index
            return (objects[link] if self._object_names else None), voxels[link], pairs[self._self_pair_link_pair], None
        centers = self._pose(q)
        near_objects = None
        if self._object_names:
            gap = np.abs(centers[:, None, :] - self._object_center[None]) - self._object_half[None]
            np.maximum(gap, 0.0, out=gap)
            near_objects = np.einsum("skj,skj->sk", gap, gap) <= self._padded_radii_sq
        i, j = self._self_pairs[:, 0], self._self_pairs[:, 1]
        offset = centers[i] - centers[j]
        near_self = np.einsum("pi,pi->p", offset, offset) <= (self._radii[i] + self._radii[j]) ** 2
        return near_objects, np.ones(len(self._links), dtype=bool), near_self, centers
