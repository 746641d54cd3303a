"""Whether a link's convex polytope keeps off a scene primitive: GJK's separation test (numba).

The sphere broad phase flags a link and an object when a covering sphere touches the object;
before this the flag stood unless one face of a box had the whole polytope beyond it
(`separating_planes.link_outside_box`), and the sphere-first search counted such a state as
blocked. In a cage or a shelf the hand passes bars and boards at an angle, and about four in
five flagged states that FCL clears were left flagged (UR5 `cage` problems), so the search
found those passages only where it asks FCL.

Gilbert, Johnson and Keerthi's algorithm walks a simplex in the Minkowski difference
polytope - object toward the origin. Any direction d along which the difference's support
point lies below zero (max over the difference of x . d < 0) proves the two apart: that
certificate is all this trusts, so a mistake in the simplex walk can only leave a pair
flagged, never clear one that touches. The object is grown by `margin_m` (a rounded
primitive), so a pair proven apart keeps that much clearance: the padded hull lies within the
hull's growth of the hull (`SphereBroadPhase._link_growth`).

Written by hand, not FCL: this runs inside the compiled lane loop for the pairs the spheres
flag, where a call out to python-fcl is not possible (and from Python costs tens of µs).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from robonav.pipeline.collision.spheres.kernels import BOX, CYLINDER, SPHERE
from robonav.pipeline.types import FloatArray, IntArray

MAX_ITERATIONS = 32
"""Simplex steps before giving up (the pair then stays flagged); GJK on such small polytopes
settles within about ten."""
CERTIFICATE_M = 1e-9
"""A support point must lie this far below the origin along the unit direction to prove separation."""


@nb.njit(cache=True)
def polytope_keeps_off(rotation: FloatArray, translation: FloatArray, vertices: FloatArray, first: int, end: int,
                       kind: int, obj_rotation: FloatArray, obj_center: FloatArray, p0: float, p1: float, p2: float,
                       margin_m: float) -> bool:  # pragma: no cover (compiled)
    """Whether the polytope with vertices[first:end] (in its own frame, placed by `rotation`
    (3, 3) and `translation` (3,)) is more than `margin_m` from the primitive `kind` (box: half
    sizes p0, p1, p2; sphere: radius p0; cylinder and capsule: radius p0, half length p1 along
    the object's z) at obj_rotation (3, 3) (world from object) and obj_center (3,).

    False means "not proven": they may touch."""
    if end <= first:
        return False
    # Simplex points (rows), newest last; d is the search direction.
    simplex = np.empty((4, 3))
    d = np.empty(3)
    point = np.empty(3)
    # First direction: from the object's center toward the polytope's first vertex.
    _place(rotation, translation, vertices, first, point)
    for i in range(3):
        d[i] = point[i] - obj_center[i]
    if d[0] * d[0] + d[1] * d[1] + d[2] * d[2] < 1e-24:
        d[0], d[1], d[2] = 1.0, 0.0, 0.0
    n = 0
    for _ in range(MAX_ITERATIONS):
        norm = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        if norm < 1e-15:
            return False  # the origin is on the simplex: touching
        _difference_support(rotation, translation, vertices, first, end, kind, obj_rotation, obj_center, p0, p1, p2,
                            margin_m, d, norm, point)
        if point[0] * d[0] + point[1] * d[1] + point[2] * d[2] < -CERTIFICATE_M * norm:
            return True
        simplex[n, 0], simplex[n, 1], simplex[n, 2] = point[0], point[1], point[2]
        n += 1
        n = _next_simplex(simplex, n, d)
        if n < 0:
            return False  # the simplex holds the origin
    return False


@nb.njit(cache=True, inline="always")
def _place(rotation: FloatArray, translation: FloatArray, vertices: FloatArray, v: int, out: FloatArray) -> None:  # pragma: no cover
    x, y, z = vertices[v, 0], vertices[v, 1], vertices[v, 2]
    for i in range(3):
        out[i] = translation[i] + rotation[i, 0] * x + rotation[i, 1] * y + rotation[i, 2] * z


@nb.njit(cache=True)
def _difference_support(rotation: FloatArray, translation: FloatArray, vertices: FloatArray, first: int, end: int,
                        kind: int, obj_rotation: FloatArray, obj_center: FloatArray, p0: float, p1: float, p2: float,
                        margin_m: float, d: FloatArray, norm: float, out: FloatArray) -> None:  # pragma: no cover
    """out = the polytope's support point along d minus the grown primitive's along -d."""
    # Polytope: the direction in its own frame, then its farthest vertex.
    lx = rotation[0, 0] * d[0] + rotation[1, 0] * d[1] + rotation[2, 0] * d[2]
    ly = rotation[0, 1] * d[0] + rotation[1, 1] * d[1] + rotation[2, 1] * d[2]
    lz = rotation[0, 2] * d[0] + rotation[1, 2] * d[1] + rotation[2, 2] * d[2]
    best, best_v = -math.inf, first
    for v in range(first, end):
        s = vertices[v, 0] * lx + vertices[v, 1] * ly + vertices[v, 2] * lz
        if s > best:
            best, best_v = s, v
    _place(rotation, translation, vertices, best_v, out)
    # Primitive along -d, in the object's frame (e = -d there).
    ex = -(obj_rotation[0, 0] * d[0] + obj_rotation[1, 0] * d[1] + obj_rotation[2, 0] * d[2])
    ey = -(obj_rotation[0, 1] * d[0] + obj_rotation[1, 1] * d[1] + obj_rotation[2, 1] * d[2])
    ez = -(obj_rotation[0, 2] * d[0] + obj_rotation[1, 2] * d[1] + obj_rotation[2, 2] * d[2])
    sx = sy = sz = 0.0
    round_m = margin_m
    if kind == BOX:
        sx, sy, sz = math.copysign(p0, ex), math.copysign(p1, ey), math.copysign(p2, ez)
    elif kind == SPHERE:
        round_m += p0
    elif kind == CYLINDER:
        sz = math.copysign(p1, ez)
        radial = math.sqrt(ex * ex + ey * ey)
        if radial > 1e-15:
            sx, sy = p0 * ex / radial, p0 * ey / radial
    else:  # CAPSULE: a segment, rounded by its radius
        sz = math.copysign(p1, ez)
        round_m += p0
    for i in range(3):
        world = obj_center[i] + obj_rotation[i, 0] * sx + obj_rotation[i, 1] * sy + obj_rotation[i, 2] * sz
        out[i] -= world - round_m * d[i] / norm


@nb.njit(cache=True, inline="always")
def _cross(ax: float, ay: float, az: float, bx: float, by: float, bz: float) -> tuple[float, float, float]:  # pragma: no cover
    return ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx


@nb.njit(cache=True, inline="always")
def _dot(ax: float, ay: float, az: float, bx: float, by: float, bz: float) -> float:  # pragma: no cover
    return ax * bx + ay * by + az * bz


@nb.njit(cache=True)
def _next_simplex(s: FloatArray, n: int, d: FloatArray) -> int:  # pragma: no cover (compiled)
    """Reduce the simplex s[:n] (newest last) to the feature nearest the origin and set d toward
    the origin from it; the new point count, or -1 when the simplex contains the origin."""
    ax, ay, az = s[n - 1, 0], s[n - 1, 1], s[n - 1, 2]
    aox, aoy, aoz = -ax, -ay, -az
    if n == 1:
        d[0], d[1], d[2] = aox, aoy, aoz
        return 1
    if n == 2:
        bx, by, bz = s[0, 0], s[0, 1], s[0, 2]
        abx, aby, abz = bx - ax, by - ay, bz - az
        if _dot(abx, aby, abz, aox, aoy, aoz) > 0:
            cx, cy, cz = _cross(abx, aby, abz, aox, aoy, aoz)
            d[0], d[1], d[2] = _cross(cx, cy, cz, abx, aby, abz)
            return 2
        s[0, 0], s[0, 1], s[0, 2] = ax, ay, az
        d[0], d[1], d[2] = aox, aoy, aoz
        return 1
    if n == 3:
        return _triangle(s, d, ax, ay, az)
    # Tetrahedron a (newest), with b = s[2], c = s[1], e = s[0]: check the three faces at a.
    bx, by, bz = s[2, 0], s[2, 1], s[2, 2]
    cx, cy, cz = s[1, 0], s[1, 1], s[1, 2]
    ex, ey, ez = s[0, 0], s[0, 1], s[0, 2]
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    aex, aey, aez = ex - ax, ey - ay, ez - az
    # Outward normals of faces abc, ace, aeb (the fourth vertex lies behind each).
    n1 = _cross(abx, aby, abz, acx, acy, acz)
    if _dot(n1[0], n1[1], n1[2], aex, aey, aez) > 0:
        n1 = (-n1[0], -n1[1], -n1[2])
    n2 = _cross(acx, acy, acz, aex, aey, aez)
    if _dot(n2[0], n2[1], n2[2], abx, aby, abz) > 0:
        n2 = (-n2[0], -n2[1], -n2[2])
    n3 = _cross(aex, aey, aez, abx, aby, abz)
    if _dot(n3[0], n3[1], n3[2], acx, acy, acz) > 0:
        n3 = (-n3[0], -n3[1], -n3[2])
    if _dot(n1[0], n1[1], n1[2], aox, aoy, aoz) > 0:  # beyond face abc: drop e
        s[0, 0], s[0, 1], s[0, 2] = cx, cy, cz
        s[1, 0], s[1, 1], s[1, 2] = bx, by, bz
        s[2, 0], s[2, 1], s[2, 2] = ax, ay, az
        return _triangle(s, d, ax, ay, az)
    if _dot(n2[0], n2[1], n2[2], aox, aoy, aoz) > 0:  # beyond face ace: drop b
        s[0, 0], s[0, 1], s[0, 2] = ex, ey, ez
        s[1, 0], s[1, 1], s[1, 2] = cx, cy, cz
        s[2, 0], s[2, 1], s[2, 2] = ax, ay, az
        return _triangle(s, d, ax, ay, az)
    if _dot(n3[0], n3[1], n3[2], aox, aoy, aoz) > 0:  # beyond face aeb: drop c
        s[0, 0], s[0, 1], s[0, 2] = bx, by, bz
        s[1, 0], s[1, 1], s[1, 2] = ex, ey, ez
        s[2, 0], s[2, 1], s[2, 2] = ax, ay, az
        return _triangle(s, d, ax, ay, az)
    return -1


@nb.njit(cache=True)
def _triangle(s: FloatArray, d: FloatArray, ax: float, ay: float, az: float) -> int:  # pragma: no cover (compiled)
    """The triangle s[0] = c, s[1] = b, s[2] = a (newest): its feature nearest the origin."""
    bx, by, bz = s[1, 0], s[1, 1], s[1, 2]
    cx, cy, cz = s[0, 0], s[0, 1], s[0, 2]
    aox, aoy, aoz = -ax, -ay, -az
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    nx, ny, nz = _cross(abx, aby, abz, acx, acy, acz)
    # Beyond edge ac (outside the triangle, on c's side of ab)?
    px, py, pz = _cross(nx, ny, nz, acx, acy, acz)
    if _dot(px, py, pz, aox, aoy, aoz) > 0:
        if _dot(acx, acy, acz, aox, aoy, aoz) > 0:  # the edge ac
            s[0, 0], s[0, 1], s[0, 2] = cx, cy, cz
            s[1, 0], s[1, 1], s[1, 2] = ax, ay, az
            t = _cross(acx, acy, acz, aox, aoy, aoz)
            d[0], d[1], d[2] = _cross(t[0], t[1], t[2], acx, acy, acz)
            return 2
        return _edge_ab_or_a(s, d, ax, ay, az, bx, by, bz)
    qx, qy, qz = _cross(abx, aby, abz, nx, ny, nz)
    if _dot(qx, qy, qz, aox, aoy, aoz) > 0:
        return _edge_ab_or_a(s, d, ax, ay, az, bx, by, bz)
    # Inside the triangle's prism: above or below its plane.
    side = _dot(nx, ny, nz, aox, aoy, aoz)
    if side > 0:
        d[0], d[1], d[2] = nx, ny, nz
        return 3
    if side < 0:  # wind the other way so the normal faces the origin
        s[0, 0], s[0, 1], s[0, 2] = bx, by, bz
        s[1, 0], s[1, 1], s[1, 2] = cx, cy, cz
        d[0], d[1], d[2] = -nx, -ny, -nz
        return 3
    return -1  # the origin lies in the triangle


@nb.njit(cache=True)
def _edge_ab_or_a(s: FloatArray, d: FloatArray, ax: float, ay: float, az: float, bx: float, by: float,
                  bz: float) -> int:  # pragma: no cover (compiled)
    aox, aoy, aoz = -ax, -ay, -az
    abx, aby, abz = bx - ax, by - ay, bz - az
    if _dot(abx, aby, abz, aox, aoy, aoz) > 0:
        s[0, 0], s[0, 1], s[0, 2] = bx, by, bz
        s[1, 0], s[1, 1], s[1, 2] = ax, ay, az
        t = _cross(abx, aby, abz, aox, aoy, aoz)
        d[0], d[1], d[2] = _cross(t[0], t[1], t[2], abx, aby, abz)
        return 2
    s[0, 0], s[0, 1], s[0, 2] = ax, ay, az
    d[0], d[1], d[2] = aox, aoy, aoz
    return 1


@nb.njit(cache=True)
def link_keeps_off_object(w: int, li: int, k: int, frames: FloatArray, link_joint: IntArray, link_whole: IntArray,
                          piece_link: IntArray, vertex_start: IntArray, vertices_joint: FloatArray, obj_kind: IntArray,
                          obj_rotation: FloatArray, obj_translation: FloatArray, obj_param: FloatArray,
                          margin_m: float) -> bool:  # pragma: no cover (compiled)
    """`polytope_keeps_off` for link li (vertices in its joint's frame, the joint placed by lane w
    of `frames`) and scene object k: its whole polytope, or else every one of its convex pieces
    (`separating_planes.link_pieces`, the rows after the whole one of the same link), which
    together hold every triangle of its meshes. A hull fills a link's concave side (the UR5's
    forearm between its joint housings), where bars and boards pass close to the mesh itself.
    """
    piece = link_whole[li]
    if piece < 0:
        return False
    j = link_joint[li]
    rotation = np.empty((3, 3))
    translation = np.empty(3)
    for r in range(3):
        for c in range(3):
            rotation[r, c] = frames[j, 3 * r + c, w]
        translation[r] = frames[j, 9 + r, w]
    kind, p0, p1, p2 = obj_kind[k], obj_param[k, 0], obj_param[k, 1], obj_param[k, 2]
    if polytope_keeps_off(rotation, translation, vertices_joint, vertex_start[piece], vertex_start[piece + 1], kind,
                          obj_rotation[k], obj_translation[k], p0, p1, p2, margin_m):
        return True
    last = piece + 1
    while last < piece_link.shape[0] and piece_link[last] == li:
        last += 1
    if last == piece + 1:
        return False  # the link is one piece: its whole polytope
    for sub in range(piece + 1, last):
        if not polytope_keeps_off(rotation, translation, vertices_joint, vertex_start[sub], vertex_start[sub + 1], kind,
                                  obj_rotation[k], obj_translation[k], p0, p1, p2, margin_m):
            return False
    return True
