"""FCL shapes of link hulls and scene objects, their bounding boxes, and the leaves of an octree.

Scene objects are FCL primitives (grown by a padding) or a BVH triangle soup; link hulls are
`fcl.Convex` shapes. `occupied_leaf_centers` expands an OctoMap binary into its leaf voxels for
the sphere broad phase.
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Sequence

import fcl
import numpy as np

from robonav.pipeline.robot.link_geometry import LinkShape
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.types import FloatArray, IntArray

OCCUPANCY = "occupancy"
"""Name reported for contacts with the occupancy octree."""


def occupied_leaf_centers(octomap_binary: bytes, resolution_m: float) -> FloatArray:
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


def octree_object(octomap_binary: bytes, resolution_m: float) -> fcl.CollisionObject | None:
    """An FCL octree of an OctoMap binary file (what `octomap.OcTree.writeBinary()` returns); None
    when it holds no node: FCL reports an empty octree as colliding with everything.

    Raises:
        ValueError: not an OctoMap binary, or its resolution is not `resolution_m`.
    """
    marker = octomap_binary.find(b"data\n")
    if not octomap_binary.startswith(b"# Octomap OcTree binary file") or marker < 0:
        raise ValueError("octomap_binary is not an octomap binary file (missing header or 'data' line)")
    header = octomap_binary[:marker].decode("ascii", errors="replace").split("\n")
    fields = dict(line.split(" ", 1) for line in header if line and not line.startswith("#") and " " in line)
    res_in_file = float(fields.get("res", "nan"))
    if not math.isclose(res_in_file, resolution_m, rel_tol=1e-6):
        raise ValueError(f"resolution_m {resolution_m} differs from the octree's own resolution {res_in_file}")
    body = octomap_binary[marker + len(b"data\n"):]
    if int(fields.get("size", "0")) == 0 or not body:
        return None
    # fcl.OcTree wants the data after the header as a sequence of C chars (signed: bytes > 127 overflow).
    return fcl.CollisionObject(fcl.OcTree(resolution_m, np.frombuffer(body, dtype=np.int8).tolist()), fcl.Transform())


def octree_of_centers(centers_m: FloatArray, resolution_m: float) -> fcl.CollisionObject | None:
    """An FCL octree whose occupied leaves are the cells of side `resolution_m` holding `centers_m`
    (N, 3) [m], on octomap's grid; None without centers."""
    import octomap

    centers = np.asarray(centers_m, dtype=np.float64).reshape(-1, 3)
    if centers.shape[0] == 0:
        return None
    tree = octomap.OcTree(resolution_m)
    tree.updateNodes(centers, True, lazy_eval=True)
    tree.updateInnerOccupancy()
    return octree_object(tree.writeBinary(), resolution_m)


def convex_shape(vertices: FloatArray, triangles: IntArray) -> fcl.Convex:
    faces = np.hstack([np.full((len(triangles), 1), 3, dtype=np.int64), triangles]).ravel()
    return fcl.Convex(np.ascontiguousarray(vertices, dtype=np.float64), len(triangles), faces)


def object_geometry(obj: SceneObject, padding_m: float = 0.0) -> fcl.CollisionGeometry:
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


def world_aabb(obj: SceneObject, world_from_object: FloatArray) -> tuple[FloatArray, FloatArray]:
    """World-frame axis-aligned box (center (3,), half extents (3,)) [m] around `obj` posed at `world_from_object`."""
    local_center, local_half = obj.local_bounds_m
    rotation = world_from_object[:3, :3]
    return rotation @ local_center + world_from_object[:3, 3], np.abs(rotation) @ local_half


def sphere_box_distance(
    centers: FloatArray, radii: FloatArray, box_center: FloatArray, box_half: FloatArray
) -> FloatArray:
    """(S, K) lower bound on the distance between spheres (S,) and axis-aligned boxes (K,) [m]."""
    gap = np.maximum(np.abs(centers[:, None, :] - box_center[None, :, :]) - box_half[None, :, :], 0.0)
    return np.sqrt(np.einsum("skj,skj->sk", gap, gap)) - radii[:, None]


class ExactLinkShapes:
    """Link shapes as their exact FCL geometry (triangle-mesh BVHs, primitives), built on first use.

    A contact of a link HULL is confirmed on these: a hull fills a link's concave pockets, and
    two such links sitting close (the UR5's forearm and wrist, its base and upper arm) touched
    as hulls in a quarter of random states where their meshes stay apart, which made valid
    starts and goals invalid; so did the UR5 forearm's hull against a table its mesh passes
    under (MotionBenchMaker's states are valid for the meshes). Only pairs whose hulls touch
    reach here, so the mesh test runs on few states (spheres and hulls clear the rest).

    Against the world with a padding, the exact shape meets the primitive grown by the padding
    (a box, cylinder, sphere or capsule grown so contains every point that near the original);
    a mesh object cannot be grown, so there the padded hull's contact stands (`padded_objects`).
    """

    def __init__(self, shapes: list[LinkShape]) -> None:
        self._shapes = shapes
        self._objs: dict[int, fcl.CollisionObject] = {}
        self._request = fcl.CollisionRequest()
        self.padded_objects: list[fcl.CollisionObject | None] = []
        """Scene objects grown by the padding, `CollisionWorld.set_objects` order; None: no exact
        confirmation of a padded contact with it (a mesh object)."""

    def build(self) -> None:
        """Build every shape's geometry now rather than at its first contact: a mesh's BVH takes
        tens of milliseconds (the UR5's gripper: about 50 ms each), which a warm-up should pay
        instead of the first query that touches that link."""
        for s, shape in enumerate(self._shapes):
            if s not in self._objs:
                self._objs[s] = fcl.CollisionObject(link_shape_geometry(shape)[0], fcl.Transform())

    def set_objects(self, objects: Sequence[SceneObject], padding_m: float) -> None:
        """The scene objects (world frame) padded contacts are confirmed against."""
        self.padded_objects = [
            None if obj.type == "mesh" and padding_m > 0 else fcl.CollisionObject(
                object_geometry(obj, padding_m), fcl.Transform(obj.world_from_object[:3, :3], obj.world_from_object[:3, 3]))
            for obj in objects]

    def collide(self, a: int, b: int, world_from_link_a: FloatArray, world_from_link_b: FloatArray) -> bool:
        """Do shapes `a` and `b` (flat shape indices) touch with their links at these (4, 4) poses?"""
        obj_a, obj_b = self._posed(a, world_from_link_a), self._posed(b, world_from_link_b)
        return fcl.collide(obj_a, obj_b, self._request, fcl.CollisionResult()) > 0

    def collide_with(self, s: int, world_from_link: FloatArray, other: fcl.CollisionObject | None) -> bool:
        """Does shape `s` with its link at (4, 4) `world_from_link` touch `other` (a posed scene
        object or octree)? None stands for an object no exact test applies to: True."""
        if other is None:
            return True
        return fcl.collide(self._posed(s, world_from_link), other, self._request, fcl.CollisionResult()) > 0

    def _posed(self, s: int, world_from_link: FloatArray) -> fcl.CollisionObject:
        obj = self._objs.get(s)
        if obj is None:
            obj = self._objs[s] = fcl.CollisionObject(link_shape_geometry(self._shapes[s])[0], fcl.Transform())
        pose = world_from_link @ self._shapes[s].link_from_shape
        obj.setRotation(pose[:3, :3])
        obj.setTranslation(pose[:3, 3])
        return obj


_geometry_of: weakref.WeakKeyDictionary[LinkShape, tuple[fcl.CollisionGeometry, FloatArray, float]] = \
    weakref.WeakKeyDictionary()


def link_shape_geometry(shape: LinkShape) -> tuple[fcl.CollisionGeometry, FloatArray, float]:
    """FCL geometry of a link shape in its SHAPE frame, with a bounding sphere (center (3,), radius) there [m].

    Built once per shape and shared: a mesh's BVH takes tens of milliseconds (the UR5's gripper
    meshes), and every planning world of a robot confirms contacts on the same shapes."""
    cached = _geometry_of.get(shape)
    if cached is None:
        cached = _geometry_of[shape] = _link_shape_geometry(shape)
    return cached


def _link_shape_geometry(shape: LinkShape) -> tuple[fcl.CollisionGeometry, FloatArray, float]:
    if shape.kind == "mesh":
        if shape.vertices is None or shape.triangles is None:
            raise ValueError(f"link '{shape.link}': mesh shape carries no triangles")
        vertices = np.ascontiguousarray(shape.vertices, dtype=np.float64)
        model = fcl.BVHModel()
        model.beginModel(len(vertices), len(shape.triangles))
        model.addSubModel(vertices, np.ascontiguousarray(shape.triangles, dtype=np.int64))
        model.endModel()
        center = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
        return model, center, float(np.max(np.linalg.norm(vertices - center, axis=1)))
    if shape.kind == "box":
        size = np.asarray(shape.size_m, dtype=np.float64)
        return fcl.Box(*size), np.zeros(3), float(0.5 * np.linalg.norm(size))
    if shape.kind == "cylinder":
        radius, length = float(shape.radius_m), float(shape.length_m)  # type: ignore[arg-type]
        return fcl.Cylinder(radius, length), np.zeros(3), math.hypot(radius, 0.5 * length)
    radius = float(shape.radius_m)  # type: ignore[arg-type]
    return fcl.Sphere(radius), np.zeros(3), radius
