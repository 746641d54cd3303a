"""Separating planes: proof that a self pair's hulls are apart where their spheres overlap.

Spheres cannot hug flat or boxy links: two links that sit a few millimetres apart in every
state (the UR5's base plate under its upper arm's shoulder housing, its wrist 2 beside the
force-torque sensor on wrist 3) keep overlapping spheres everywhere, so every state went to
FCL and the sphere-first search gave up. For such a pair, a few face planes of one link's hull
(in that link's frame) are picked at construction; at a state where the pair's spheres touch,
the pair is clear when every vertex of the other link's hull lies strictly outside one of those
planes (the plane then separates the two hulls, so FCL would find no contact either). The test
is a few hundred multiply-adds in the compiled check instead of a call to FCL.

The planes are chosen on seeded random states: greedily, those that separate the pair at most
of the states where its spheres touch. They only save work: a state they do not clear is
flagged as before, so the answers stay those of the spheres and FCL.

A link hull with many vertices is replaced by a polytope around it (the hull's supporting
planes along fixed directions), which contains it: the test stays sound and short.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import fcl
import numba as nb
import numpy as np
from scipy.spatial import ConvexHull, HalfspaceIntersection

from robonav.pipeline.collision.fcl_shapes import convex_shape
from robonav.pipeline.robot.lane_kinematics import LinkKinematics
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.types import FloatArray, IntArray

MAX_VERTICES = 128
"""A link hull with more vertices is tested as its bounding polytope along `_DIRECTIONS` directions."""
PLANES_PER_PAIR = 4
SAMPLE_STATES = 96
"""Seeded random states the planes are chosen on."""
GUARD_M = 1e-5
"""Every vertex must clear the plane by this much: far above rounding, far below any padding."""
_DIRECTIONS = 66
_SEED = 0


@dataclass(frozen=True)
class SeparatingPlanes:
    """Planes per self pair and link vertices, as flat arrays for compiled code (joint frames).

    Attributes:
        pair_start: (P + 1,) the planes of pair p are rows pair_start[p]:pair_start[p + 1].
        owner: (C,) collision link whose hull lies inside plane c (n . x + d <= 0).
        plane_joint: (C, 4) the plane (n, d) in the owner's joint frame; n has unit length.
        vertex_start: (L + 1,) the vertices of link l are rows vertex_start[l]:vertex_start[l + 1].
        vertices_joint: (V, 3) hull (or bounding polytope) vertices in their link's joint frame [m].
    """

    pair_start: IntArray
    owner: IntArray
    plane_joint: FloatArray
    vertex_start: IntArray
    vertices_joint: FloatArray

    @staticmethod
    def none(n_pairs: int, n_links: int) -> SeparatingPlanes:
        return SeparatingPlanes(np.zeros(n_pairs + 1, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros((0, 4)),
                                np.zeros(n_links + 1, dtype=np.int64), np.zeros((0, 3)))


def link_polytope(vertices_m: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Vertices (V, 3) and face planes (F, 4) (n . x + d <= 0 inside, |n| = 1) of a convex polytope
    containing the points `vertices_m` (N, 3): their hull, or when it has more than
    `MAX_VERTICES` vertices the intersection of their supporting half-spaces along fixed directions."""
    points = np.asarray(vertices_m, dtype=np.float64).reshape(-1, 3)
    hull = ConvexHull(points)
    if len(hull.vertices) <= MAX_VERTICES:
        planes = np.unique(np.round(hull.equations, 12), axis=0)
        return points[hull.vertices].copy(), planes
    i = np.arange(_DIRECTIONS) + 0.5
    polar, azimuth = np.arccos(1 - 2 * i / _DIRECTIONS), math.pi * (1 + 5**0.5) * i
    normals = np.column_stack([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)])
    normals = np.vstack([normals, np.eye(3), -np.eye(3)])
    planes = np.column_stack([normals, -(points @ normals.T).max(axis=0)])
    interior = points[hull.vertices].mean(axis=0)
    corners = HalfspaceIntersection(planes, interior).intersections
    return corners, planes


def build_separating_planes(robot: RobotModel, kin: LinkKinematics, centers_link: FloatArray, radii_m: FloatArray,
                            link_start: IntArray, self_pairs: IntArray) -> SeparatingPlanes:
    """Planes for the self pairs (P, 2) whose spheres (`centers_link` (S, 3) in link frames,
    `radii_m`, link l's spheres link_start[l]:link_start[l + 1]) touch at some sampled state."""
    links = robot.collision_link_names
    n_links = len(links)
    polytopes = [link_polytope(np.vstack([s.hull_vertices for s in robot.link_collision_shapes[link]]))
                 for link in links]
    shapes = [fcl.CollisionObject(convex_shape(*_hull_of(p[0])), fcl.Transform()) for p in polytopes]
    rng = np.random.default_rng(_SEED)
    states = rng.uniform(robot.lower_limits_rad, robot.upper_limits_rad, size=(SAMPLE_STATES, robot.dof))
    poses = np.stack([robot.link_pose_stack(q) for q in states])  # (M, L, 4, 4) world_from_link
    owner_of = _sphere_links(link_start)
    placed = poses[:, owner_of]  # (M, S, 4, 4)
    spheres = np.einsum("msij,sj->msi", placed[..., :3, :3], centers_link) + placed[..., :3, 3]
    pair_start, owners, planes = [0], [], []
    for la, lb in self_pairs:
        a, b = slice(link_start[la], link_start[la + 1]), slice(link_start[lb], link_start[lb + 1])
        gap = np.linalg.norm(spheres[:, a, None] - spheres[:, None, b], axis=3) - radii_m[a, None] - radii_m[None, b]
        touching = np.flatnonzero((gap <= 0).any(axis=(1, 2)))
        chosen: list[tuple[int, FloatArray]] = []
        if touching.size:
            candidates = []  # (owner, plane in the owner's link frame, separated at each touching state)
            for owner, other in ((la, lb), (lb, la)):
                other_in_owner = np.linalg.inv(poses[touching, owner]) @ poses[touching, other]  # (T, 4, 4)
                vertices = np.einsum("tij,vj->tvi", other_in_owner[:, :3, :3], polytopes[other][0]) \
                    + other_in_owner[:, None, :3, 3]
                own = polytopes[owner][0]
                # The owner's face planes, and at each state where the polytopes are apart the
                # plane normal to their shortest connection (it separates where no face does).
                normals = np.vstack([polytopes[owner][1][:, :3], _nearest_normals(
                    shapes[owner], shapes[other], other_in_owner)])
                tried = np.column_stack([normals, -(own @ normals.T).max(axis=0)])
                clearance = (vertices @ tried[:, :3].T + tried[:, 3]).min(axis=1)  # (T, F)
                candidates += [(owner, plane, clearance[:, f] > GUARD_M) for f, plane in enumerate(tried)]
            left = np.ones(touching.size, dtype=bool)
            for _ in range(PLANES_PER_PAIR):
                gains = [int(np.count_nonzero(sep & left)) for _, _, sep in candidates]
                best = int(np.argmax(gains)) if gains else -1
                if best < 0 or gains[best] == 0:
                    break
                owner, plane, sep = candidates[best]
                chosen.append((owner, plane))
                left &= ~sep
        for owner, plane in chosen:
            owners.append(owner)
            planes.append(_plane_to_joint(kin, owner, plane, polytopes[owner][0]))
        pair_start.append(len(owners))
    vertex_start = np.zeros(n_links + 1, dtype=np.int64)
    vertex_start[1:] = np.cumsum([len(p[0]) for p in polytopes])
    vertices = np.vstack([kin_points(kin, li, p[0]) for li, p in enumerate(polytopes)])
    return SeparatingPlanes(np.array(pair_start, dtype=np.int64), np.array(owners, dtype=np.int64),
                            np.array(planes, dtype=np.float64).reshape(-1, 4), vertex_start,
                            np.ascontiguousarray(vertices))


_planes_of: weakref.WeakKeyDictionary[RobotModel, dict[bytes, SeparatingPlanes]] = weakref.WeakKeyDictionary()


def cached_separating_planes(robot: RobotModel, kin: LinkKinematics, centers_link: FloatArray, radii_m: FloatArray,
                             link_start: np.ndarray, self_pairs: np.ndarray) -> SeparatingPlanes:
    """`build_separating_planes`, once per robot, spheres and pair list (every planning world of a
    robot has the same)."""
    key = b"".join(np.ascontiguousarray(x).tobytes() for x in (centers_link, radii_m, link_start, self_pairs))
    per_robot = _planes_of.setdefault(robot, {})
    if key not in per_robot:
        per_robot[key] = build_separating_planes(robot, kin, centers_link, radii_m, link_start, self_pairs)
    return per_robot[key]


def kin_points(kin: LinkKinematics, link: int, points_link: FloatArray) -> FloatArray:
    """(N, 3) points of collision link `link`'s frame in its joint's frame."""
    return points_link @ kin.joint_from_link_rotation[link].T + kin.joint_from_link_translation_m[link]


def _plane_to_joint(kin: LinkKinematics, link: int, plane: FloatArray, owner_vertices: FloatArray) -> FloatArray:
    normal = kin.joint_from_link_rotation[link] @ plane[:3]
    # The offset from the owner's own vertices, so they lie inside exactly as the test sees them.
    offset = -float((kin_points(kin, link, owner_vertices) @ normal).max())
    return np.array([*normal, offset])


def _hull_of(points: FloatArray) -> tuple[FloatArray, IntArray]:
    hull = ConvexHull(points)
    return points, hull.simplices


def _nearest_normals(owner: fcl.CollisionObject, other: fcl.CollisionObject, other_in_owner: FloatArray) -> FloatArray:
    """(N, 3) unit directions from `owner` (at the identity) to `other` (at each of `other_in_owner`
    (T, 4, 4)) along their shortest connection, where they are apart."""
    request = fcl.DistanceRequest(enable_nearest_points=True)
    owner.setTransform(fcl.Transform())
    out = []
    for pose in other_in_owner:
        other.setTransform(fcl.Transform(pose[:3, :3], pose[:3, 3]))
        result = fcl.DistanceResult()
        if fcl.distance(owner, other, request, result) > GUARD_M:
            direction = np.asarray(result.nearest_points[1]) - np.asarray(result.nearest_points[0])
            norm = float(np.linalg.norm(direction))
            if norm > GUARD_M:
                out.append(direction / norm)
    return np.array(out).reshape(-1, 3)


def _sphere_links(link_start: IntArray) -> IntArray:
    return np.repeat(np.arange(len(link_start) - 1), np.diff(link_start))


@nb.njit(cache=True, inline="always")
def pair_separated(w: int, p: int, la: int, lb: int, frames: FloatArray, link_joint: IntArray, pair_start: IntArray,
                   owner: IntArray, plane_joint: FloatArray, vertex_start: IntArray,
                   vertices_joint: FloatArray) -> bool:  # pragma: no cover (compiled)
    """Whether one of self pair p's planes separates links la and lb in lane w of `frames`."""
    for c in range(pair_start[p], pair_start[p + 1]):
        o = owner[c]
        other = lb if o == la else la
        jo, jt = link_joint[o], link_joint[other]
        n0, n1, n2, d = plane_joint[c, 0], plane_joint[c, 1], plane_joint[c, 2], plane_joint[c, 3]
        # The plane in the world: normal R_o n, offset d - (R_o n) . t_o.
        w0 = frames[jo, 0, w] * n0 + frames[jo, 1, w] * n1 + frames[jo, 2, w] * n2
        w1 = frames[jo, 3, w] * n0 + frames[jo, 4, w] * n1 + frames[jo, 5, w] * n2
        w2 = frames[jo, 6, w] * n0 + frames[jo, 7, w] * n1 + frames[jo, 8, w] * n2
        dw = d - (w0 * frames[jo, 9, w] + w1 * frames[jo, 10, w] + w2 * frames[jo, 11, w])
        # ... and in the other link's joint frame: normal R_t^T n_w, offset n_w . t_t + d_w.
        m0 = frames[jt, 0, w] * w0 + frames[jt, 3, w] * w1 + frames[jt, 6, w] * w2
        m1 = frames[jt, 1, w] * w0 + frames[jt, 4, w] * w1 + frames[jt, 7, w] * w2
        m2 = frames[jt, 2, w] * w0 + frames[jt, 5, w] * w1 + frames[jt, 8, w] * w2
        c0 = w0 * frames[jt, 9, w] + w1 * frames[jt, 10, w] + w2 * frames[jt, 11, w] + dw
        apart = True
        for v in range(vertex_start[other], vertex_start[other + 1]):
            if m0 * vertices_joint[v, 0] + m1 * vertices_joint[v, 1] + m2 * vertices_joint[v, 2] + c0 <= GUARD_M:
                apart = False
                break
        if apart:
            return True
    return False
