"""Collision checking of a robot against itself, primitive scene objects and an occupancy octree (FCL).

Every robot shape is an `fcl.Convex` of its convex hull (GJK on a hull is much faster than on
the triangle mesh). A hull contains its mesh, so this is conservative: it can report contact in
a concave pocket of a link where the mesh itself is free. Robot-vs-world checks use hulls grown
by `padding_m` (see `link_geometry.grow_hull`); self-collision and clearance use the ungrown hulls.

Each check first rejects pairs whose bounding spheres cannot touch (numpy), then runs FCL per
pair in Python. Against FCL's DynamicAABBTree managers (Panda, 6 boxes and a 53k-leaf octree)
this measured 140 vs 165 us on random states and 210 vs 178 us on free ones: a wash, so the
simpler per-pair form won; it also names the colliding objects, which python-fcl's manager
callbacks cannot (they receive anonymous copies of the objects).
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import fcl
import numpy as np
import numpy.typing as npt

from robonav.pipeline.collision.spheres.broad_phase import SphereBroadPhase
from robonav.pipeline.robot.link_geometry import grow_hull
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.types import FloatArray, IntArray, StateValidFn

OCCUPANCY = "occupancy"
"""Name reported for contacts with the occupancy octree."""
SELF_OVERFLAG_PROBES = 64
"""Random states `sphere_self_overflag` measures on (seeded, so the figure is reproducible)."""
_self_overflag: weakref.WeakKeyDictionary[RobotModel, float] = weakref.WeakKeyDictionary()


class CollisionWorld:
    """A robot model plus the obstacles it must avoid, all in the robot base (world) frame.

    Not thread-safe: FCL objects are re-posed on every query.
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
                self._objs.append(fcl.CollisionObject(_convex(vertices, triangles), fcl.Transform()))
                self._padded_objs.append(fcl.CollisionObject(_convex(grown_v, grown_t), fcl.Transform()))
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
             if self._links[i] != self._links[j]
             and tuple(sorted((self._links[i], self._links[j]))) not in ignored],
            dtype=np.int64,
        ).reshape(-1, 2)
        self._request = fcl.CollisionRequest()
        self._distance_request = fcl.DistanceRequest()
        self._octree: fcl.CollisionObject | None = None
        self._seen_voxels_m: FloatArray | None = None
        self._octree_resolution_m = 0.0
        self._object_names: list[str] = []
        self._object_fcl: list[fcl.CollisionObject] = []
        self._object_center = np.zeros((0, 3))
        self._object_half = np.zeros((0, 3))
        self._posed: list[int] = [0] * n
        self._posed_padded: list[int] = [0] * n
        self._generation = 0
        self._revision = 0
        self._world_from_shape_link = np.zeros((n, 4, 4))
        self._attached: dict[str, _Attached] = {}
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
                   seen_voxels_m: npt.ArrayLike | None = None) -> None:
        """Replace the occupancy map with an octree in the world frame.

        Args:
            octomap_binary: What `octomap.OcTree.writeBinary()` returns (header and data).
            resolution_m: Leaf size [m]; must match the `res` line of the header.
            seen_voxels_m: (N, 3) centers of the voxels the sensors saw, when the octree is
                those grown by an inflation (`Occupancy.occupied_centers_m`) [m]; None: unknown.
        """
        self._revision += 1
        if not (math.isfinite(resolution_m) and resolution_m > 0):
            raise ValueError(f"resolution_m must be finite and > 0, got {resolution_m}")
        seen = None if seen_voxels_m is None else np.asarray(seen_voxels_m, dtype=np.float64)
        if seen is not None and (seen.ndim != 2 or seen.shape[1] != 3 or not np.all(np.isfinite(seen))):
            raise ValueError(f"seen_voxels_m must be a finite (N, 3) array, got shape {seen.shape}")
        marker = octomap_binary.find(b"data\n")
        if not octomap_binary.startswith(b"# Octomap OcTree binary file") or marker < 0:
            raise ValueError("octomap_binary is not an octomap binary file (missing header or 'data' line)")
        header = octomap_binary[:marker].decode("ascii", errors="replace").split("\n")
        fields = dict(line.split(" ", 1) for line in header if line and not line.startswith("#") and " " in line)
        res_in_file = float(fields.get("res", "nan"))
        if not math.isclose(res_in_file, resolution_m, rel_tol=1e-6):
            raise ValueError(f"resolution_m {resolution_m} differs from the octree's own resolution {res_in_file}")
        # Only a map that passed the checks above replaces the seen voxels of the last one.
        self._seen_voxels_m = seen
        self._octree_resolution_m = float(resolution_m)
        body = octomap_binary[marker + len(b"data\n"):]
        if int(fields.get("size", "0")) == 0 or not body:
            # FCL reports an empty octree as colliding with everything; an empty map has no obstacles.
            self._octree = None
            if self._broad_phase is not None:
                self._broad_phase.clear_occupancy()
            return
        # fcl.OcTree wants the data after the header as a sequence of C chars (signed: bytes > 127 overflow).
        tree = fcl.OcTree(resolution_m, np.frombuffer(body, dtype=np.int8).tolist())
        self._octree = fcl.CollisionObject(tree, fcl.Transform())
        if self._broad_phase is not None:
            self._broad_phase.set_occupied_voxels(_occupied_leaf_centers(octomap_binary, resolution_m), resolution_m)

    @property
    def seen_voxels_m(self) -> FloatArray | None:
        """(N, 3) centers of the map's voxels before inflation, side `octree_resolution_m` [m];
        None when the map came without them (or there is no map)."""
        return self._seen_voxels_m

    @property
    def octree_resolution_m(self) -> float:
        """Leaf size of the current map [m]; 0 without one."""
        return self._octree_resolution_m

    def clear_octree(self) -> None:
        self._revision += 1
        self._octree = None
        self._seen_voxels_m = None
        self._octree_resolution_m = 0.0
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
            fcl_objs.append(fcl.CollisionObject(_object_geometry(obj), fcl.Transform(pose[:3, :3], pose[:3, 3])))
            center, half = _world_aabb(obj, pose)
            centers.append(center)
            halves.append(half)
        self._object_names, self._object_fcl = names, fcl_objs
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
        return tuple(a.info for a in self._attached.values())

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
        if (q is None) == (world_from_link is None):
            raise ValueError("attach_object needs exactly one of q and world_from_link")
        home = self._robot.home_position_rad
        for i, name in enumerate((link, *touch_links)):
            try:
                self._robot.frame_pose(home, name)  # raises for names that are not frames of the robot
            except ValueError as exc:
                raise ValueError(f"{'link' if i == 0 else f'touch_links[{i - 1}]'}: {exc}") from exc
        if world_from_link is None:
            world_from_link = self._robot.frame_pose(self._robot.validate_q(q, "q"), link)
        pose = np.asarray(world_from_link, dtype=np.float64)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise ValueError(f"world_from_link must be a finite (4, 4) transform, got shape {pose.shape}")
        link_from_object = np.linalg.inv(pose) @ obj.world_from_object
        link_from_object.setflags(write=False)
        info = AttachedObject(obj.with_pose(link_from_object), link, tuple(touch_links), link_from_object)
        allowed = {link, *touch_links}
        shape_index = self._links.index(link) if link in self._links else -1
        self._attached.pop(obj.name, None)
        self._attached[obj.name] = _Attached(
            info=info,
            obj=fcl.CollisionObject(_object_geometry(obj), fcl.Transform()),
            padded_obj=fcl.CollisionObject(_object_geometry(obj, self._padding_m), fcl.Transform()),
            local_bounds=obj.local_bounds_m,
            shape_index=shape_index,
            checked_shapes=np.array([lk not in allowed for lk in self._links], dtype=bool),
        )
        return info

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
        if name not in self._attached:
            raise ValueError(f"no attached object named '{name}' (attached: {sorted(self._attached)})")
        world_pose = None if q is None else self.attached_world_from_object(name, q)
        info = self._attached.pop(name).info
        return None if world_pose is None else info.object.with_pose(world_pose)

    def attached_world_from_object(self, name: str, q: FloatArray) -> FloatArray:
        """(4, 4) world pose of the attached object `name` with the robot at `q` (dof,)."""
        if name not in self._attached:
            raise ValueError(f"no attached object named '{name}' (attached: {sorted(self._attached)})")
        info = self._attached[name].info
        return self._robot.frame_pose(q, info.link) @ info.link_from_object

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
        if self._broad_phase_usable() and not self._broad_phase.state_suspect(self._robot.validate_q(q)):
            return False
        return bool(self._check(q, first_only=True))

    def touches_cubes(self, q: FloatArray, centers_m: FloatArray, side_m: float) -> bool:
        """True when a padded link at `q` touches one of the axis-aligned cubes of edge `side_m`
        centered at `centers_m` (N, 3), e.g. voxels. Only the robot, none of the world's objects.

        Cheaper than `set_objects` + `in_collision` for a few voxels checked once: no
        SceneObjects and no broad phase rebuilt, one shared box shape, an AABB test first."""
        centers = self._pose(self._robot.validate_q(q))
        cubes = np.asarray(centers_m, dtype=np.float64).reshape(-1, 3)
        gap = np.maximum(np.abs(centers[:, None, :] - cubes[None]) - 0.5 * side_m, 0.0)
        near = np.einsum("skj,skj->sk", gap, gap) <= self._padded_radii_sq
        cube = fcl.Box(side_m, side_m, side_m)
        for s, k in zip(*np.nonzero(near)):
            if self._collide(self._posed_obj(int(s), padded=True), fcl.CollisionObject(cube, fcl.Transform(cubes[k]))):
                return True
        return False

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
        # The spheres contain the padded hulls: when they touch nothing, neither does FCL.
        if self._broad_phase_usable() and not self._broad_phase.state_suspect(self._robot.validate_q(q)):
            return []
        return self._check(q, first_only=False, padded=padded)

    def clearance_m(self, q: FloatArray) -> float:
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
            lower = _sphere_box_distance(centers, self._radii, self._object_center, self._object_half)
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

    def min_clearance_m(self, states: FloatArray) -> float:
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
        for flat in np.argsort(bounds, axis=None, kind="stable"):
            m, link, k = np.unravel_index(flat, bounds.shape)
            if bounds[m, link, k] >= best or best <= 0.0:
                break
            if m != posed:
                self._set_link_poses(poses[m])
                posed = m
            for s in self._shapes_of_link[link]:
                best = min(best, self._distance(self._posed_obj(s, padded=False), obstacles[k]))
        return best

    def _attached_clearance_m(self, q: FloatArray) -> float:
        """Smallest distance [m] from the unpadded attached objects to the objects and octree; needs `_pose(q)` first."""
        best = math.inf
        for attached, _, _ in self._pose_attached(q):
            for other in (*self._object_fcl, *([self._octree] if self._octree is not None else [])):
                best = min(best, self._distance(attached.obj, other))
        return best

    def _pose_attached(self, q: FloatArray) -> list[tuple[_Attached, FloatArray, FloatArray]]:
        """Poses every attached object for the FK of the last `_pose(q)`; (object, world AABB center (3,), half extents (3,))."""
        out = []
        for attached in self._attached.values():
            s = attached.shape_index
            world_from_link = (self._world_from_shape_link[s] if s >= 0
                               else self._robot.frame_pose(q, attached.info.link))
            world_from_object = world_from_link @ attached.info.link_from_object
            for obj in (attached.obj, attached.padded_obj):
                obj.setRotation(world_from_object[:3, :3])
                obj.setTranslation(world_from_object[:3, 3])
            center, half = _world_aabb(attached.info.object, world_from_object)
            out.append((attached, center, half))
        return out

    def _check_attached(self, q: FloatArray, centers: FloatArray, hits: list[tuple[str, str]], *, first_only: bool) -> None:
        """Appends (attached object, link / object / 'occupancy') pairs that touch; needs `_pose(q)` first."""
        posed = self._pose_attached(q)
        for attached, center, half in posed:
            name = attached.info.name
            candidates: list[tuple[str, fcl.CollisionObject, fcl.CollisionObject]] = []
            if self._object_names:
                near = np.all(np.abs(self._object_center - center) <= self._object_half + half + self._padding_m, axis=1)
                candidates += [(self._object_names[k], attached.padded_obj, self._object_fcl[k]) for k in np.flatnonzero(near)]
            if self._octree is not None:
                candidates.append((OCCUPANCY, attached.padded_obj, self._octree))
            offsets = centers - center
            radius = float(np.linalg.norm(half))
            near_shapes = (np.einsum("si,si->s", offsets, offsets) <= (self._radii + radius) ** 2) & attached.checked_shapes
            candidates += [(self._links[s], attached.obj, self._posed_obj(int(s), padded=False)) for s in np.flatnonzero(near_shapes)]
            for other, a, b in candidates:
                if (name, other) not in hits and self._collide(a, b):
                    hits.append((name, other))
                    if first_only:
                        return
        for i, (first, center_a, half_a) in enumerate(posed):
            for second, center_b, half_b in posed[i + 1:]:
                # Two objects on one link keep their relative pose: like adjacent links, never checked.
                if first.info.link == second.info.link or np.any(np.abs(center_a - center_b) > half_a + half_b):
                    continue
                if self._collide(first.obj, second.obj):
                    hits.append((first.info.name, second.info.name))
                    if first_only:
                        return

    def motion_valid(self, q_a: FloatArray, q_b: FloatArray, resolution_rad: float) -> bool:
        """True when every state on the straight joint-space segment from `q_a` to `q_b` is free.

        States are spaced at most `resolution_rad` apart in every joint; both ends are checked.
        The end `q_b` is checked first, then the interior in bisection order, then `q_a`, so a
        blocked edge is usually rejected after a few states.
        """
        a = self._robot.validate_q(q_a, "q_a")
        b = self._robot.validate_q(q_b, "q_b")
        if self._broad_phase_usable():
            return self._suspects_free(a, b, resolution_rad, lambda _q: True)
        steps = _step_count(a, b, resolution_rad)
        if self._check(b, first_only=True):
            return False
        for k in _bisection_order(steps):
            if self._check(a + (b - a) * (k / steps), first_only=True):
                return False
        return not self._check(a, first_only=True)

    @property
    def spheres_usable(self) -> bool:
        """Whether `state_free_by_spheres` / `motion_free_by_spheres` use the sphere model (else
        they are `in_collision` / `motion_valid`)."""
        return self._broad_phase_usable()

    def sphere_self_overflag(self) -> float:
        """Share of self-collision-free random states at which the spheres of a self-collision
        pair touch anyway (0 when the sphere model is not used). Measured once per robot.

        Near 1 when a config checks a pair whose spheres always touch although the hulls do not
        (e.g. open fingers not allowed to touch): every state is then suspect, and the
        sphere-first search can find nothing."""
        if not self._broad_phase_usable():
            return 0.0
        cached = _self_overflag.get(self._robot)
        if cached is None:
            rng = np.random.default_rng(0)
            robot = self._robot
            states = rng.uniform(robot.lower_limits_rad, robot.upper_limits_rad, size=(SELF_OVERFLAG_PROBES, robot.dof))
            pairs = self.self_collision_pairs
            free = [q for q in states if not self.link_pairs_in_collision(q, pairs)]
            cached = sum(self._broad_phase.self_suspect(q) for q in free) / max(len(free), 1)
            _self_overflag[self._robot] = cached
        return cached

    def state_free_by_spheres(self, q: FloatArray, exact: StateValidFn) -> bool:
        """Conservative validity of `q`: free when its spheres touch nothing; when they do, FCL
        decides only if `exact(q)`, else the state counts as in collision.

        Sound (a state it calls free is FCL-free) and, away from where `exact` holds, FCL-free:
        the planner's fast mode, which gives up states the spheres over-cover for speed."""
        if not self._broad_phase_usable():
            return not self.in_collision(q)
        q = self._robot.validate_q(q)
        if not self._broad_phase.state_suspect(q):
            return True
        return bool(exact(q)) and not self._check(q, first_only=True)

    def motion_free_by_spheres(self, q_a: FloatArray, q_b: FloatArray, resolution_rad: float,
                               exact: StateValidFn) -> bool:
        """`motion_valid` at the same states, each judged as by `state_free_by_spheres`."""
        if not self._broad_phase_usable():
            return self.motion_valid(q_a, q_b, resolution_rad)
        return self._suspects_free(self._robot.validate_q(q_a, "q_a"), self._robot.validate_q(q_b, "q_b"),
                                   resolution_rad, exact)

    def _suspects_free(self, a: FloatArray, b: FloatArray, resolution_rad: float,
                       exact: StateValidFn) -> bool:
        """The edge's broad-phase suspects, in `motion_valid` order, are each either asked of
        FCL (where `exact`) and free, or none exist. The first suspect is tried alone first
        because a blocked edge's first suspect usually is a collision."""
        first, steps = self._broad_phase.edge_suspects(a, b, resolution_rad, first_only=True)
        if first.size == 0:
            return True
        q = a + (b - a) * (first[0] / steps)
        if not exact(q) or self._check(q, first_only=True):
            return False
        suspects, _ = self._broad_phase.edge_suspects(a, b, resolution_rad)
        for k in suspects[1:]:
            q = a + (b - a) * (k / steps)
            if not exact(q) or self._check(q, first_only=True):
                return False
        return True

    def path_valid(self, path: FloatArray, resolution_rad: float) -> bool:
        """True when every segment of `path` (K, dof), K >= 1, passes `motion_valid`."""
        arr = self._path(path)
        if arr.shape[0] == 1:
            return not self.in_collision(arr[0])
        return all(self.motion_valid(arr[i], arr[i + 1], resolution_rad) for i in range(arr.shape[0] - 1))

    def path_clearance_m(self, path: FloatArray, resolution_rad: float) -> float:
        """Smallest `clearance_m` over `path` (K, dof) sampled at most `resolution_rad` apart [m]."""
        arr = self._path(path)
        states = [arr[0]]
        for i in range(arr.shape[0] - 1):
            steps = _step_count(arr[i], arr[i + 1], resolution_rad)
            states += [arr[i] + (arr[i + 1] - arr[i]) * (k / steps) for k in range(1, steps + 1)]
        return self.min_clearance_m(np.array(states))

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

    def _check(self, q: FloatArray, *, first_only: bool, padded: bool = True) -> list[tuple[str, str]]:
        near_objects, near_octree, near_self, centers = self._near_pairs(q)
        hits: list[tuple[str, str]] = []
        links = self._links
        if near_objects is not None:
            for s, k in zip(*np.nonzero(near_objects)):
                pair = (links[s], self._object_names[k])
                if pair not in hits and self._collide(self._posed_obj(int(s), padded=padded), self._object_fcl[k]):
                    hits.append(pair)
                    if first_only:
                        return hits
        if self._octree is not None:
            for s in np.flatnonzero(near_octree):
                pair = (links[s], OCCUPANCY)
                if pair not in hits and self._collide(self._posed_obj(int(s), padded=padded), self._octree):
                    hits.append(pair)
                    if first_only:
                        return hits
        for a, b in self._self_pairs[near_self]:
            pair = (links[a], links[b])
            if pair in hits:
                continue
            if self._collide(self._posed_obj(int(a), padded=False), self._posed_obj(int(b), padded=False)):
                hits.append(pair)
                if first_only:
                    return hits
        if self._attached:
            self._check_attached(q, centers, hits, first_only=first_only)
        return hits

    def _near_pairs(self, q: FloatArray):  # noqa: ANN202 - four arrays
        """Pose the robot at `q` and say which pairs FCL must test.

        Returns (S, K) shape-object and (S,) shape-octree masks, a mask over `_self_pairs` (the
        object mask is None without objects) and the shapes' centers (S, 3), or None for them
        when the sphere model answered: then only pairs whose spheres touch are tested (the
        spheres contain the padded hulls, so no other pair can collide), which saves most FCL
        calls and the culling here; otherwise bounding spheres against the objects' boxes cull."""
        if self._broad_phase_usable():
            objects, voxels, pairs, poses = self._broad_phase.suspect_pairs(self._robot.validate_q(q))
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


def _occupied_leaf_centers(octomap_binary: bytes, resolution_m: float) -> FloatArray:
    """(N, 3) centers [m] of the occupied leaf-size voxels of an octomap binary (pruned nodes expanded)."""
    import octomap  # only worlds with an occupancy map need it

    tree = octomap.OcTree(resolution_m)
    if not tree.readBinary(octomap_binary):
        raise ValueError("octomap_binary could not be read by octomap")
    centers: list[FloatArray] = []
    for leaf in tree.begin_leafs():
        if not tree.isNodeOccupied(leaf):
            continue
        size = leaf.getSize()
        center = np.asarray(leaf.getCoordinate(), dtype=np.float64)
        width = int(round(size / resolution_m))
        if width <= 1:
            centers.append(center[None])
        else:
            offsets = (np.arange(width) - 0.5 * (width - 1)) * resolution_m
            grid = np.stack(np.meshgrid(offsets, offsets, offsets, indexing="ij"), axis=-1).reshape(-1, 3)
            centers.append(center + grid)
    return np.vstack(centers) if centers else np.zeros((0, 3))


def _convex(vertices: FloatArray, triangles: IntArray) -> fcl.Convex:
    faces = np.hstack([np.full((len(triangles), 1), 3, dtype=np.int64), triangles]).ravel()
    return fcl.Convex(np.ascontiguousarray(vertices, dtype=np.float64), len(triangles), faces)


@dataclass(frozen=True, eq=False)
class AttachedObject:
    """An object fixed to a robot link."""

    object: SceneObject
    """The object, posed in the LINK frame (its `world_from_object` is link_from_object)."""
    link: str
    """The robot frame it moves with."""
    touch_links: tuple[str, ...]
    """Robot links it may touch besides `link`."""
    link_from_object: FloatArray
    """(4, 4) pose of the object in the link frame."""

    @property
    def name(self) -> str:
        return self.object.name


@dataclass(frozen=True, eq=False)
class _Attached:
    info: AttachedObject
    obj: fcl.CollisionObject
    padded_obj: fcl.CollisionObject
    local_bounds: tuple[FloatArray, FloatArray]
    shape_index: int
    """A robot shape of `info.link` (its pose is the link's), or -1 for a link without geometry."""
    checked_shapes: npt.NDArray[np.bool_]
    """(S,) robot shapes the object is checked against (not on `link` or `touch_links`)."""


def _object_geometry(obj: SceneObject, padding_m: float = 0.0) -> fcl.CollisionGeometry:
    """FCL geometry of a scene object in its own frame, primitives grown by `padding_m` (meshes are not)."""
    pad = padding_m
    if obj.type == "box":
        return fcl.Box(*(s + 2 * pad for s in obj.size_m))
    if obj.type == "cylinder":
        return fcl.Cylinder(obj.radius_m + pad, obj.length_m + 2 * pad)
    if obj.type == "sphere":
        return fcl.Sphere(obj.radius_m + pad)
    if obj.type == "capsule":
        return fcl.Capsule(obj.radius_m + pad, obj.length_m)
    # A triangle soup: FCL tests surfaces, so a shape entirely inside a closed mesh is not a contact.
    model = fcl.BVHModel()
    model.beginModel(len(obj.vertices_m), len(obj.triangles))
    model.addSubModel(np.ascontiguousarray(obj.vertices_m), np.ascontiguousarray(obj.triangles, dtype=np.int32))
    model.endModel()
    return model


def _world_aabb(obj: SceneObject, world_from_object: FloatArray) -> tuple[FloatArray, FloatArray]:
    """World-frame axis-aligned box (center (3,), half extents (3,)) [m] around `obj` posed at `world_from_object`."""
    local_center, local_half = obj.local_bounds_m
    rotation = world_from_object[:3, :3]
    return rotation @ local_center + world_from_object[:3, 3], np.abs(rotation) @ local_half


def _sphere_box_distance(
    centers: FloatArray, radii: FloatArray, box_center: FloatArray, box_half: FloatArray
) -> FloatArray:
    """(S, K) lower bound on the distance between spheres (S,) and axis-aligned boxes (K,) [m]."""
    gap = np.maximum(np.abs(centers[:, None, :] - box_center[None, :, :]) - box_half[None, :, :], 0.0)
    return np.sqrt(np.einsum("skj,skj->sk", gap, gap)) - radii[:, None]


def _step_count(a: FloatArray, b: FloatArray, resolution_rad: float) -> int:
    if not (math.isfinite(resolution_rad) and resolution_rad > 0):
        raise ValueError(f"resolution_rad must be finite and > 0, got {resolution_rad}")
    return max(1, math.ceil(float(np.max(np.abs(b - a))) / resolution_rad - 1e-9))


@lru_cache(maxsize=256)
def _bisection_order(steps: int) -> tuple[int, ...]:
    """Interior indices 1..steps-1, midpoints of ever finer halvings first."""
    order, queue = [], [(0, steps)]
    while queue:
        next_queue = []
        for lo, hi in queue:
            if hi - lo < 2:
                continue
            mid = (lo + hi) // 2
            order.append(mid)
            next_queue += [(lo, mid), (mid, hi)]
        queue = next_queue
    return tuple(order)
