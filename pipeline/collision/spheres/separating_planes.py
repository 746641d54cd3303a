"""Separating planes: proof that a self pair's hulls are apart where their spheres overlap.

Spheres cannot hug flat or boxy links: two links that sit a few millimetres apart in every
state (the UR5's base plate under its upper arm's shoulder housing, its wrist 2 beside the
force-torque sensor on wrist 3) keep overlapping spheres everywhere, so every state went to
FCL and the sphere-first search gave up. Their hulls touch often too (the base plate and the
upper arm's hull in a third of random states, their meshes in 3 %), so each link is cut into
up to `PIECES` convex pieces: its mesh triangles clustered (k-means on their centroids, seeded),
each cluster's hull a piece; the pieces hold every triangle, so pieces apart means meshes apart
(FCL's exact test is on the triangles). For a self pair, a few planes per pair of pieces are
picked at construction; at a state where the pair's spheres touch, the pair is clear when every
pair of pieces has bounding spheres apart or a plane with every vertex of one piece strictly
outside and the other piece inside. The test is some hundred multiply-adds in the compiled
check instead of FCL calls from Python.

The planes are chosen on seeded random states among the pieces' face planes and the planes
normal to their shortest connection: greedily, those that separate the pieces at most of the
states where the pair's spheres touch. They only save work: a state they do not clear is
flagged as before, and a state they clear is free on the meshes, as FCL would find it.

A piece with many vertices is replaced by a polytope around it (its supporting planes along
fixed directions), which contains it: the test stays sound and short.
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Sequence
from dataclasses import dataclass

import fcl
import numba as nb
import numpy as np
from scipy.cluster.vq import kmeans2
from scipy.spatial import ConvexHull, HalfspaceIntersection

from robonav.pipeline.collision.fcl_shapes import convex_shape
from robonav.pipeline.collision.spheres.table_store import dataclass_from_arrays, dataclass_to_arrays, stored, table_key
from robonav.pipeline.robot.lane_kinematics import LinkKinematics
from robonav.pipeline.robot.link_geometry import LinkShape
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.transforms import transform_points
from robonav.pipeline.types import FloatArray, IntArray

MAX_VERTICES = 128
"""A piece with more vertices is tested as its bounding polytope along `_DIRECTIONS` directions."""
PIECES = 5
"""Convex pieces a mesh link is cut into (on the UR5, piece hulls touch about as rarely as the meshes)."""
PLANES_PER_PIECE_PAIR = 8
SAMPLE_STATES = 160
"""Seeded random states the planes are chosen on."""
GUARD_M = 1e-5
"""Every vertex must clear the plane by this much: far above rounding, far below any padding."""
_DIRECTIONS = 66
_SEED = 0


@dataclass(frozen=True)
class SeparatingPlanes:
    """Pieces of the collision links and planes per self pair, flat arrays for compiled code.

    Attributes:
        pair_whole: (P,) row of `sub_piece` holding pair p's two whole links (their hulls'
            polytopes, tried first: one plane often does), -1 for none.
        pair_range: (P, 2) pair p's pairs of pieces are rows pair_range[p, 0]:pair_range[p, 1] of
            `sub_piece`, all of which must be apart; none: the pieces are not tried.
        sub_piece: (B, 2) pieces of the pair's first and second link.
        sub_start: (B + 1,) planes of piece pair b are rows sub_start[b]:sub_start[b + 1].
        side: (C,) 0: plane c lies in the frame of the first piece's link and holds that piece
            inside (n . x + d <= 0), the other piece's vertices are tested; 1: the other way.
        plane_joint: (C, 4) plane (n, d), in its link's joint frame; |n| = 1.
        piece_link: (K,) collision link of each piece.
        piece_center_joint: (K, 3) bounding sphere centers in their link's joint frame [m].
        piece_radius: (K,) bounding sphere radii [m].
        vertex_start: (K + 1,) vertices of piece k are rows vertex_start[k]:vertex_start[k + 1].
        vertices_joint: (V, 3) piece vertices in their link's joint frame [m].
        link_whole: (L,) the piece that is a whole link's polytope (tested against scene boxes),
            -1 for none.
    """

    pair_whole: IntArray
    pair_range: IntArray
    sub_piece: IntArray
    sub_start: IntArray
    side: IntArray
    plane_joint: FloatArray
    piece_link: IntArray
    piece_center_joint: FloatArray
    piece_radius: FloatArray
    vertex_start: IntArray
    vertices_joint: FloatArray
    link_whole: IntArray

    @staticmethod
    def none(n_pairs: int, n_links: int) -> SeparatingPlanes:
        ints = np.zeros(0, dtype=np.int64)
        return SeparatingPlanes(np.full(n_pairs, -1, dtype=np.int64), np.zeros((n_pairs, 2), dtype=np.int64),
                                np.zeros((0, 2), dtype=np.int64),
                                np.zeros(1, dtype=np.int64), ints, np.zeros((0, 4)), ints, np.zeros((0, 3)),
                                np.zeros(0), np.zeros(1, dtype=np.int64), np.zeros((0, 3)),
                                np.full(n_links, -1, dtype=np.int64))


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


def link_pieces(shapes: Sequence[LinkShape], pieces: int = PIECES) -> list[FloatArray]:
    """Point sets (N, 3) in the link frame whose convex hulls hold every triangle of the link's
    meshes (k-means clusters of the triangles) and its primitives' hulls, one set each."""
    out = []
    for shape in shapes:
        if shape.kind != "mesh" or shape.vertices is None or shape.triangles is None:
            out.append(shape.hull_vertices)
            continue
        vertices = transform_points(shape.link_from_shape, shape.vertices)
        triangles = shape.triangles
        k = min(pieces, max(1, len(triangles) // 8))
        found: list[FloatArray] = []
        if k > 1:
            _, label = kmeans2(vertices[triangles].mean(axis=1), k, seed=_SEED, minit="++")
            for c in range(k):
                points = vertices[np.unique(triangles[label == c])]
                if len(points) and not _solid(points):
                    found = []  # a flat cluster: keep the whole hull instead
                    break
                if len(points):
                    found.append(points)
        out += found or [shape.hull_vertices]
    return out


def build_separating_planes(robot: RobotModel, kin: LinkKinematics, centers_link: FloatArray, radii_m: FloatArray,
                            link_start: IntArray, self_pairs: IntArray) -> SeparatingPlanes:
    """Planes for the self pairs (P, 2) whose spheres (`centers_link` (S, 3) in link frames,
    `radii_m`, link l's spheres link_start[l]:link_start[l + 1]) touch at some sampled state."""
    links = robot.collision_link_names
    piece_link, polytopes, whole, piece_rows = [], [], [], []
    for li, link in enumerate(links):
        shapes_of_link = robot.link_collision_shapes[link]
        whole.append(len(polytopes))
        piece_link.append(li)
        polytopes.append(link_polytope(np.vstack([s.hull_vertices for s in shapes_of_link])))
        cut = link_pieces(shapes_of_link)
        piece_rows.append([whole[-1]] if len(cut) == 1 else list(range(len(polytopes), len(polytopes) + len(cut))))
        for points in cut if len(cut) > 1 else []:
            piece_link.append(li)
            polytopes.append(link_polytope(points))
    piece_link_arr = np.array(piece_link, dtype=np.int64)
    shapes = [fcl.CollisionObject(convex_shape(vertices, ConvexHull(vertices).simplices), fcl.Transform())
              for vertices, _ in polytopes]
    centers = np.array([0.5 * (v.min(axis=0) + v.max(axis=0)) for v, _ in polytopes]).reshape(-1, 3)
    radii = np.array([float(np.linalg.norm(v - c, axis=1).max()) for (v, _), c in zip(polytopes, centers)])
    rng = np.random.default_rng(_SEED)
    states = rng.uniform(robot.lower_limits_rad, robot.upper_limits_rad, size=(SAMPLE_STATES, robot.dof))
    poses = np.stack([robot.link_pose_stack(q) for q in states])  # (M, L, 4, 4) world_from_link
    owner_of = _sphere_links(link_start)
    placed = poses[:, owner_of]  # (M, S, 4, 4)
    spheres = np.einsum("msij,sj->msi", placed[..., :3, :3], centers_link) + placed[..., :3, 3]
    pair_whole = np.full(len(self_pairs), -1, dtype=np.int64)
    pair_range = np.zeros((len(self_pairs), 2), dtype=np.int64)
    sub_piece, sub_start, sides, planes = [], [0], [], []

    def add(i: int, j: int, chosen: list[tuple[int, FloatArray]], la: int, lb: int) -> None:
        sub_piece.append((i, j))
        for side, plane in chosen:
            sides.append(side)
            planes.append(_plane_to_joint(kin, la if side == 0 else lb, plane, polytopes[i if side == 0 else j][0]))
        sub_start.append(len(sides))

    for p, (la, lb) in enumerate(self_pairs):
        a, b = slice(link_start[la], link_start[la + 1]), slice(link_start[lb], link_start[lb + 1])
        gap = np.linalg.norm(spheres[:, a, None] - spheres[:, None, b], axis=3) - radii_m[a, None] - radii_m[None, b]
        touching = np.flatnonzero((gap <= 0).any(axis=(1, 2)))
        pair_range[p] = len(sub_piece)
        if touching.size == 0:
            continue
        b_in_a = np.linalg.inv(poses[touching, la]) @ poses[touching, lb]  # (T, 4, 4)
        chosen, by_whole = _piece_planes(polytopes, shapes, centers, radii, whole[la], whole[lb], b_in_a)
        if chosen:
            pair_whole[p] = len(sub_piece)
            add(whole[la], whole[lb], chosen, la, lb)
        if by_whole.all() or (len(piece_rows[la]) == 1 and len(piece_rows[lb]) == 1):
            pair_range[p] = len(sub_piece)
            continue
        rows = []
        cleared = np.ones(touching.size, dtype=bool)
        for i in piece_rows[la]:
            for j in piece_rows[lb]:
                chosen, separated = _piece_planes(polytopes, shapes, centers, radii, i, j, b_in_a)
                rows.append((i, j, chosen))
                cleared &= separated
        pair_range[p, 0] = len(sub_piece)
        if np.any(cleared & ~by_whole):  # else the pieces add nothing: leave the rest to FCL at no cost
            for i, j, chosen in rows:
                add(i, j, chosen, la, lb)
        pair_range[p, 1] = len(sub_piece)
    vertex_start = np.zeros(len(polytopes) + 1, dtype=np.int64)
    vertex_start[1:] = np.cumsum([len(v) for v, _ in polytopes])
    vertices = np.vstack([kin_points(kin, piece_link[k], v) for k, (v, _) in enumerate(polytopes)])
    return SeparatingPlanes(
        pair_whole, pair_range, np.array(sub_piece, dtype=np.int64).reshape(-1, 2),
        np.array(sub_start, dtype=np.int64), np.array(sides, dtype=np.int64),
        np.array(planes, dtype=np.float64).reshape(-1, 4), piece_link_arr,
        np.ascontiguousarray(np.array([kin_points(kin, piece_link[k], centers[k][None])[0] for k in range(len(centers))]
                                      ).reshape(-1, 3)),
        radii, vertex_start, np.ascontiguousarray(vertices), np.array(whole, dtype=np.int64))


def _piece_planes(polytopes: list[tuple[FloatArray, FloatArray]], shapes: list[fcl.CollisionObject],
                  centers: FloatArray, radii: FloatArray, i: int, j: int,
                  j_in_i: FloatArray) -> tuple[list[tuple[int, FloatArray]], np.ndarray]:
    """Up to `PLANES_PER_PIECE_PAIR` planes (side, plane in that side's link frame) for pieces i and j
    at the link poses `j_in_i` (T, 4, 4), and at which of those states the pieces are proven apart."""
    center_j = np.einsum("tij,j->ti", j_in_i[:, :3, :3], centers[j]) + j_in_i[:, :3, 3]
    apart = np.linalg.norm(center_j - centers[i], axis=1) > radii[i] + radii[j] + GUARD_M
    if apart.all():
        return [], apart
    near = ~apart
    poses = j_in_i[near]
    inverse = np.linalg.inv(poses)
    candidates = []  # (side, plane, separated at each near state)
    for side, own, other, other_in_own in ((0, i, j, poses), (1, j, i, inverse)):
        vertices = np.einsum("tij,vj->tvi", other_in_own[:, :3, :3], polytopes[other][0]) + other_in_own[:, None, :3, 3]
        normals = np.vstack([polytopes[own][1][:, :3], _nearest_normals(shapes[own], shapes[other], other_in_own)])
        tried = np.column_stack([normals, -(polytopes[own][0] @ normals.T).max(axis=0)])
        clearance = (vertices @ tried[:, :3].T + tried[:, 3]).min(axis=1)  # (T, F)
        candidates += [(side, plane, clearance[:, f] > GUARD_M) for f, plane in enumerate(tried)]
    left = np.ones(poses.shape[0], dtype=bool)
    chosen = []
    for _ in range(PLANES_PER_PIECE_PAIR):
        gains = [int(np.count_nonzero(sep & left)) for _, _, sep in candidates]
        best = int(np.argmax(gains))
        if gains[best] == 0:
            break
        side, plane, sep = candidates[best]
        chosen.append((side, plane))
        left &= ~sep
    separated = apart.copy()
    separated[near] = ~left
    return chosen, separated


def _solid(points: FloatArray) -> bool:
    """Whether the points span a volume (not all on a plane or a line)."""
    if len(points) < 4:
        return False
    centered = points - points.mean(axis=0)
    return bool(np.linalg.svd(centered, compute_uv=False)[-1] > 1e-6 * max(1.0, float(np.abs(centered).max())))


_planes_of: weakref.WeakKeyDictionary[RobotModel, dict[str, SeparatingPlanes]] = weakref.WeakKeyDictionary()


def cached_separating_planes(robot: RobotModel, kin: LinkKinematics, centers_link: FloatArray, radii_m: FloatArray,
                             link_start: np.ndarray, self_pairs: np.ndarray) -> SeparatingPlanes:
    """`build_separating_planes`, once per robot, spheres and pair list (every planning world of a
    robot has the same), kept in the installed `TableStore` too."""
    # Everything the builder reads: the links' shapes, the kinematics and limits its sampled states use.
    shapes = [robot.link_collision_shapes[link] for link in robot.collision_link_names]
    key = table_key("separating-planes", robot.collision_link_names, [[shape_key(s) for s in of_link] for of_link in shapes],
                    kin, robot.lower_limits_rad, robot.upper_limits_rad, centers_link, radii_m, link_start, self_pairs)
    per_robot = _planes_of.setdefault(robot, {})
    if key not in per_robot:
        per_robot[key] = stored(key, lambda: build_separating_planes(robot, kin, centers_link, radii_m, link_start,
                                                                     self_pairs),
                                dataclass_to_arrays, dataclass_from_arrays(SeparatingPlanes))
    return per_robot[key]


def shape_key(shape: LinkShape) -> tuple:
    """A shape as the builder sees it: its geometry, not the file it came from."""
    return (shape.link, shape.kind, shape.link_from_shape, shape.hull_vertices, shape.hull_triangles, shape.vertices,
            shape.triangles, shape.size_m, shape.radius_m, shape.length_m)


def joint_frame_pieces(robot: RobotModel, kin: LinkKinematics) -> list[list[FloatArray]]:
    """Per collision link, the vertices (N, 3) of the convex pieces the planes are chosen for, in
    the link's joint frame: the pieces of `link_pieces`, or the whole link when it is one piece."""
    out = []
    for li, link in enumerate(robot.collision_link_names):
        shapes = robot.link_collision_shapes[link]
        if not shapes:
            out.append([])
            continue
        cut = link_pieces(shapes)
        sets = [np.vstack([s.hull_vertices for s in shapes])] if len(cut) == 1 else cut
        out.append([kin_points(kin, li, link_polytope(points)[0]) for points in sets])
    return out


def kin_points(kin: LinkKinematics, link: int, points_link: FloatArray) -> FloatArray:
    """(N, 3) points of collision link `link`'s frame in its joint's frame."""
    return points_link @ kin.joint_from_link_rotation[link].T + kin.joint_from_link_translation_m[link]


def _plane_to_joint(kin: LinkKinematics, link: int, plane: FloatArray, owner_vertices: FloatArray) -> FloatArray:
    normal = kin.joint_from_link_rotation[link] @ plane[:3]
    # The offset from the owner's own vertices, so they lie inside exactly as the test sees them.
    offset = -float((kin_points(kin, link, owner_vertices) @ normal).max())
    return np.array([*normal, offset])


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


@nb.njit(cache=True)
def _pieces_apart(w: int, s: int, frames: FloatArray, link_joint: IntArray, sub_piece: IntArray, sub_start: IntArray,
                  side: IntArray, plane_joint: FloatArray, piece_link: IntArray, piece_center: FloatArray,
                  piece_radius: FloatArray, vertex_start: IntArray, vertices_joint: FloatArray) -> bool:  # pragma: no cover
    """Whether the pieces of row s of `sub_piece` are proven apart in lane w: bounding spheres or a plane."""
    i, j = sub_piece[s, 0], sub_piece[s, 1]
    ji, jj = link_joint[piece_link[i]], link_joint[piece_link[j]]
    dx = dy = dz = 0.0
    for r in range(3):
        ci = frames[ji, 9 + r, w] + frames[ji, 3 * r, w] * piece_center[i, 0] \
            + frames[ji, 3 * r + 1, w] * piece_center[i, 1] + frames[ji, 3 * r + 2, w] * piece_center[i, 2]
        cj = frames[jj, 9 + r, w] + frames[jj, 3 * r, w] * piece_center[j, 0] \
            + frames[jj, 3 * r + 1, w] * piece_center[j, 1] + frames[jj, 3 * r + 2, w] * piece_center[j, 2]
        if r == 0:
            dx = ci - cj
        elif r == 1:
            dy = ci - cj
        else:
            dz = ci - cj
    reach = piece_radius[i] + piece_radius[j] + GUARD_M
    if dx * dx + dy * dy + dz * dz > reach * reach:
        return True
    apart = False
    for c in range(sub_start[s], sub_start[s + 1]):
        own, other = (i, j) if side[c] == 0 else (j, i)
        jo, jt = link_joint[piece_link[own]], link_joint[piece_link[other]]
        n0, n1, n2, d = plane_joint[c, 0], plane_joint[c, 1], plane_joint[c, 2], plane_joint[c, 3]
        # The plane in the world: normal R_o n, offset d - (R_o n) . t_o.
        w0 = frames[jo, 0, w] * n0 + frames[jo, 1, w] * n1 + frames[jo, 2, w] * n2
        w1 = frames[jo, 3, w] * n0 + frames[jo, 4, w] * n1 + frames[jo, 5, w] * n2
        w2 = frames[jo, 6, w] * n0 + frames[jo, 7, w] * n1 + frames[jo, 8, w] * n2
        dw = d - (w0 * frames[jo, 9, w] + w1 * frames[jo, 10, w] + w2 * frames[jo, 11, w])
        # ... and in the other piece's joint frame: normal R_t^T n_w, offset n_w . t_t + d_w.
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
            break
    return apart


@nb.njit(cache=True)
def pair_separated(w: int, p: int, frames: FloatArray, link_joint: IntArray, pair_whole: IntArray, pair_range: IntArray,
                   sub_piece: IntArray, sub_start: IntArray, side: IntArray, plane_joint: FloatArray,
                   piece_link: IntArray, piece_center: FloatArray, piece_radius: FloatArray, vertex_start: IntArray,
                   vertices_joint: FloatArray) -> bool:  # pragma: no cover (compiled)
    """Whether self pair p is proven apart in lane w of `frames`: its whole links, or every pair of pieces."""
    if pair_whole[p] >= 0 and _pieces_apart(w, pair_whole[p], frames, link_joint, sub_piece, sub_start, side,
                                             plane_joint, piece_link, piece_center, piece_radius, vertex_start,
                                             vertices_joint):
        return True
    if pair_range[p, 0] == pair_range[p, 1]:
        return False
    for s in range(pair_range[p, 0], pair_range[p, 1]):
        if not _pieces_apart(w, s, frames, link_joint, sub_piece, sub_start, side, plane_joint, piece_link,
                             piece_center, piece_radius, vertex_start, vertices_joint):
            return False
    return True


@nb.njit(cache=True)
def link_outside_box(w: int, li: int, k: int, frames: FloatArray, link_joint: IntArray, link_whole: IntArray,
                     vertex_start: IntArray, vertices_joint: FloatArray, obj_rotation: FloatArray,
                     obj_translation: FloatArray, obj_param: FloatArray, margin: float) -> bool:  # pragma: no cover
    """Whether every vertex of link li's polytope lies beyond one face of box k by more than
    `margin` in lane w (a face plane of the box then separates them: no sphere test needed)."""
    piece = link_whole[li]
    if piece < 0:
        return False
    j = link_joint[li]
    outside = np.ones(6, dtype=np.bool_)
    for v in range(vertex_start[piece], vertex_start[piece + 1]):
        px, py, pz = vertices_joint[v, 0], vertices_joint[v, 1], vertices_joint[v, 2]
        dx = frames[j, 9, w] + frames[j, 0, w] * px + frames[j, 1, w] * py + frames[j, 2, w] * pz - obj_translation[k, 0]
        dy = frames[j, 10, w] + frames[j, 3, w] * px + frames[j, 4, w] * py + frames[j, 5, w] * pz - obj_translation[k, 1]
        dz = frames[j, 11, w] + frames[j, 6, w] * px + frames[j, 7, w] * py + frames[j, 8, w] * pz - obj_translation[k, 2]
        some = False
        for a in range(3):
            u = obj_rotation[k, 0, a] * dx + obj_rotation[k, 1, a] * dy + obj_rotation[k, 2, a] * dz
            limit = obj_param[k, a] + margin + GUARD_M
            outside[2 * a] &= u > limit
            outside[2 * a + 1] &= u < -limit
            some |= outside[2 * a] | outside[2 * a + 1]
        if not some:
            return False
    return True
