"""Sphere covers of convex shapes: every robot link as a few spheres that contain its collision hulls.

The sphere broad phase (`pipeline/broad_phase.py`) is only allowed to clear a state when the
exact FCL check would clear it too, so the spheres must CONTAIN each link's convex hull, not just
approximate it (VAMP's Panda spheres do not: FORMAT.md of the MBM benchmark finds 29 % of its
paths touching obstacles).

Algorithm (deterministic): the hull's volume is sampled uniformly, k-means splits the samples
into k clusters, and the hull is cut into the k Voronoi cells of the cluster centers. Each cell
is a convex polytope whose vertices are computed exactly (qhull half-space intersection), and
its sphere is the smallest ball around those vertices (Welzl). A ball containing a convex
polytope's vertices contains the polytope, and the cells partition the hull, so the cover is
exact by construction; dense samples of the surface and the interior are then checked anyway,
and `tolerance_m` is added to every radius. k grows from 1 until no sphere reaches more than
`max_protrusion_m` beyond the hull (support-function excess), or `max_spheres` is reached.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache

import fcl
import numpy as np
from scipy.optimize import linprog
from scipy.spatial import ConvexHull, HalfspaceIntersection

from robonav.pipeline.collision.spheres.table_store import stored, table_key
from robonav.pipeline.robot.link_geometry import LinkShape, grow_hull
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.types import FloatArray, IntArray

DEFAULT_TOLERANCE_M = 2.5e-4
"""Added to every radius: covers rounding in qhull/Welzl and FCL's GJK tolerance [m]."""
DEFAULT_MAX_PROTRUSION_M = 0.015
"""Default bound on how far a sphere may reach beyond the hull it covers [m]."""
DEFAULT_MAX_SPHERES = 12
"""Default cap on the spheres of one convex shape."""
_TARGET_SAMPLES = 2400
_LEFTOVER_FRACTION = 0.03
_CANDIDATES = 1000
_CHECK_SAMPLES = 6000
_DIRECTIONS = 600
_SEED = 0


@dataclass(frozen=True)
class SphereCover:
    """Spheres covering one convex point set.

    Attributes:
        centers_m: (S, 3) sphere centers, in the frame of the input points [m].
        radii_m: (S,) radii, tolerance included [m].
        hull_volume_m3: Volume of the convex hull covered [m^3].
        union_volume_m3: Monte-Carlo estimate of the volume of the union of the spheres [m^3].
        max_protrusion_m: Largest distance any sphere reaches beyond the hull (support-function
            excess over sampled directions) [m].
    """

    centers_m: FloatArray
    radii_m: FloatArray
    hull_volume_m3: float
    union_volume_m3: float
    max_protrusion_m: float


@dataclass(frozen=True)
class RobotSphereModel:
    """Spheres rigid on the collision links of a robot, each covering one link shape's hull.

    Attributes:
        link_names: Collision links, `RobotModel.collision_link_names` order.
        centers_link_m: (S, 3) sphere centers, each in ITS link's frame [m].
        radii_m: (S,) radii [m] (unpadded: they cover the hulls themselves).
        link_index: (S,) index into `link_names` of each sphere's link; spheres of one link are
            contiguous and links appear in order.
        shape_index: (S,) index of the covered shape in the flat list of all link shapes
            (`link_collision_shapes` iterated in order, as `CollisionWorld` numbers them).
        covers: One `SphereCover` per shape, same flat order.
    """

    link_names: tuple[str, ...]
    centers_link_m: FloatArray
    radii_m: FloatArray
    link_index: IntArray
    shape_index: IntArray
    covers: tuple[SphereCover, ...]

    @property
    def sphere_count(self) -> int:
        return int(self.radii_m.shape[0])

    @property
    def hull_volume_m3(self) -> float:
        """Summed hull volume of all shapes [m^3]."""
        return float(sum(c.hull_volume_m3 for c in self.covers))

    @property
    def union_volume_m3(self) -> float:
        """Summed per-shape sphere-union volume (Monte-Carlo estimate) [m^3]."""
        return float(sum(c.union_volume_m3 for c in self.covers))


def cover_convex_points(
    points_m: FloatArray,
    *,
    max_protrusion_m: float = DEFAULT_MAX_PROTRUSION_M,
    max_spheres: int = DEFAULT_MAX_SPHERES,
    tolerance_m: float = DEFAULT_TOLERANCE_M,
) -> SphereCover:
    """Spheres whose union contains the convex hull of `points_m` (any convex shape's vertices).

    Use it for anything given by points whose hull contains it: a link mesh, or a box's 8
    corners or a polygonal prism around a cylinder for an attached object.

    Args:
        points_m: (N, 3) points, N >= 4, not all coplanar; any frame [m].
        max_protrusion_m: Stop adding spheres once none reaches further than this beyond the hull [m].
        max_spheres: Upper bound on the sphere count.
        tolerance_m: Added to every radius [m]; dense samples are checked against the radii without it.

    Returns:
        The cover, centers in the frame of `points_m`.

    Raises:
        ValueError: bad arguments, or the coverage check failed (a bug, not an input problem).
    """
    pts = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    if pts.shape[0] < 4 or not np.all(np.isfinite(pts)):
        raise ValueError(f"points_m must hold at least 4 finite points, got shape {np.shape(points_m)}")
    if not (max_spheres >= 1 and max_protrusion_m >= 0 and tolerance_m >= 0):
        raise ValueError(f"need max_spheres >= 1, max_protrusion_m >= 0, tolerance_m >= 0; got "
                         f"{max_spheres}, {max_protrusion_m}, {tolerance_m}")
    return _cover_cached(pts.tobytes(), pts.shape[0], float(max_protrusion_m), int(max_spheres), float(tolerance_m))


def robot_sphere_model(
    robot: RobotModel,
    *,
    max_protrusion_m: float = DEFAULT_MAX_PROTRUSION_M,
    max_spheres_per_shape: int = DEFAULT_MAX_SPHERES,
    tolerance_m: float = DEFAULT_TOLERANCE_M,
) -> RobotSphereModel:
    """Cover every collision shape of every checked link of `robot` with spheres (link frames).

    Covers are cached in-process by hull, so building several worlds for one robot is cheap, and
    the whole model in the installed `TableStore` between processes.
    """
    links = robot.collision_link_names
    hulls = [shape.hull_vertices for link in links for shape in robot.link_collision_shapes[link]]
    key = table_key("spheres", links, hulls, float(max_protrusion_m), int(max_spheres_per_shape), float(tolerance_m))
    model = stored(key, lambda: _build_robot_sphere_model(robot, max_protrusion_m, max_spheres_per_shape, tolerance_m),
                   _sphere_model_arrays, lambda arrays: _sphere_model_of_arrays(links, arrays))
    for arr in (model.centers_link_m, model.radii_m, model.link_index, model.shape_index):
        arr.setflags(write=False)
    return model


def _build_robot_sphere_model(robot: RobotModel, max_protrusion_m: float, max_spheres_per_shape: int,
                              tolerance_m: float) -> RobotSphereModel:
    centers, radii, link_index, shape_index, covers = [], [], [], [], []
    links = robot.collision_link_names
    flat = 0
    for li, link in enumerate(links):
        for shape in robot.link_collision_shapes[link]:
            cover = cover_convex_points(shape.hull_vertices, max_protrusion_m=max_protrusion_m,
                                        max_spheres=max_spheres_per_shape, tolerance_m=tolerance_m)
            covers.append(cover)
            centers.append(cover.centers_m)
            radii.append(cover.radii_m)
            link_index.append(np.full(cover.radii_m.shape[0], li, dtype=np.int64))
            shape_index.append(np.full(cover.radii_m.shape[0], flat, dtype=np.int64))
            flat += 1
    model = RobotSphereModel(
        link_names=links,
        centers_link_m=np.vstack(centers).reshape(-1, 3),
        radii_m=np.concatenate(radii),
        link_index=np.concatenate(link_index),
        shape_index=np.concatenate(shape_index),
        covers=tuple(covers),
    )
    for arr in (model.centers_link_m, model.radii_m, model.link_index, model.shape_index):
        arr.setflags(write=False)
    return model


def _sphere_model_arrays(model: RobotSphereModel) -> dict[str, np.ndarray]:
    return {"centers_link_m": model.centers_link_m, "radii_m": model.radii_m, "link_index": model.link_index,
            "shape_index": model.shape_index,
            "cover_counts": np.array([len(c.radii_m) for c in model.covers], dtype=np.int64),
            "cover_volumes": np.array([(c.hull_volume_m3, c.union_volume_m3, c.max_protrusion_m) for c in model.covers],
                                      dtype=np.float64).reshape(-1, 3)}


def _sphere_model_of_arrays(links: tuple[str, ...], arrays: Mapping[str, np.ndarray]) -> RobotSphereModel:
    """A model saved by `_sphere_model_arrays`; each cover's spheres are its rows of the model's."""
    centers, radii = arrays["centers_link_m"], arrays["radii_m"]
    counts, volumes = arrays["cover_counts"], arrays["cover_volumes"]
    if counts.sum() != len(radii) or len(volumes) != len(counts) or centers.shape != (len(radii), 3):
        raise ValueError("stored sphere model does not add up")
    starts = np.concatenate([[0], np.cumsum(counts)])
    covers = tuple(SphereCover(centers[a:b].copy(), radii[a:b].copy(), float(v[0]), float(v[1]), float(v[2]))
                   for a, b, v in zip(starts[:-1], starts[1:], volumes))
    return RobotSphereModel(link_names=links, centers_link_m=centers, radii_m=radii, link_index=arrays["link_index"],
                            shape_index=arrays["shape_index"], covers=covers)


def radii_covering(points_m: FloatArray, centers_m: FloatArray, radii_m: FloatArray, *,
                   tolerance_m: float = DEFAULT_TOLERANCE_M) -> FloatArray:
    """Radii with which the balls at `centers_m` cover the convex hull of `points_m` (e.g. a link
    hull grown by a padding, covered by the link's own spheres): `radii_m` grown where needed.

    Each ball grows just enough to cover its power cell of the hull (`_exact_radii`), which is
    tighter than adding the hull's worst growth to every radius: a padding grows a hull by about
    itself along faces but by up to 1.8 times at sharp vertices, and only the balls there need it.

    Raises:
        ValueError: bad shapes, or the coverage check failed (a bug, not an input problem).
    """
    pts = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    centers = np.asarray(centers_m, dtype=np.float64).reshape(-1, 3)
    radii = np.asarray(radii_m, dtype=np.float64).reshape(-1)
    if pts.shape[0] < 4 or centers.shape[0] == 0 or radii.shape[0] != centers.shape[0]:
        raise ValueError(f"need >= 4 points and one radius per center, got {pts.shape}, {centers.shape}, {radii.shape}")
    hull = ConvexHull(pts)
    equations = np.unique(np.round(hull.equations, 12), axis=0)
    out = _exact_radii(equations, centers, radii)
    _check_coverage(equations, pts[hull.vertices], pts, hull, centers, out, np.random.default_rng(_SEED))
    return out + tolerance_m


def box_points(size_m: tuple[float, float, float] | FloatArray) -> FloatArray:
    """(8, 3) corners of a box with full side lengths `size_m`, centered at the origin [m]."""
    half = 0.5 * np.asarray(size_m, dtype=np.float64)
    return np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64) * half


def cylinder_points(radius_m: float, length_m: float, sides: int = 24) -> FloatArray:
    """(2 * sides, 3) prism corners around a cylinder along z (apothem = radius), centered at the origin [m]."""
    angles = np.arange(sides) * (2 * math.pi / sides)
    rim = radius_m / math.cos(math.pi / sides)
    ring = np.column_stack([rim * np.cos(angles), rim * np.sin(angles)])
    return np.vstack([np.column_stack([ring, np.full(sides, z)]) for z in (-0.5 * length_m, 0.5 * length_m)])


@lru_cache(maxsize=512)
def _cover_cached(points_bytes: bytes, n: int, max_protrusion_m: float, max_spheres: int,
                  tolerance_m: float) -> SphereCover:
    pts = np.frombuffer(points_bytes, dtype=np.float64).reshape(n, 3)
    hull = ConvexHull(pts)
    vertices = pts[hull.vertices]
    # Merge coplanar triangle facets: fewer half-spaces for every cell intersection.
    equations = np.unique(np.round(hull.equations, 12), axis=0)
    rng = np.random.default_rng(_SEED)
    targets = np.vstack([_surface_samples(pts, hull, _TARGET_SAMPLES, rng),
                         _volume_samples(equations, vertices, _TARGET_SAMPLES // 2, rng)])
    candidates = _volume_samples(equations, vertices, _CANDIDATES, rng)
    # Depth of an interior point = distance to the boundary = smallest distance to a face plane.
    depth = np.maximum(-(candidates @ equations[:, :3].T + equations[:, 3]).max(axis=1), 0.0)
    centers, radii = _greedy_cover(candidates, depth + max_protrusion_m, targets, max_spheres)
    radii = _exact_radii(equations, centers, radii)
    _check_coverage(equations, vertices, pts, hull, centers, radii, rng)
    radii = radii + tolerance_m
    directions = _fibonacci_directions(_DIRECTIONS)
    hull_support = (directions @ vertices.T).max(axis=1)
    excess = float(((directions @ centers.T) + radii[None, :] - hull_support[:, None]).max())
    union = _union_volume(centers, radii, rng)
    centers.setflags(write=False)
    radii.setflags(write=False)
    return SphereCover(centers, radii, float(hull.volume), union, excess)


def _greedy_cover(candidates: FloatArray, candidate_radii: FloatArray, targets: FloatArray,
                  max_spheres: int) -> tuple[FloatArray, FloatArray]:
    """Greedy set cover of `targets` (T, 3) by candidate balls (C, 3)/(C,): largest gain first."""
    d2 = (np.sum(candidates**2, axis=1)[:, None] + np.sum(targets**2, axis=1)[None, :]
          - 2.0 * candidates @ targets.T)
    covers = (d2 <= candidate_radii[:, None] ** 2).astype(np.float32)
    uncovered = np.ones(targets.shape[0], dtype=bool)
    chosen: list[int] = []
    # The last few percent of samples sit in corners; chasing them adds many small spheres, so
    # stop early and let `_exact_radii` grow the chosen balls over what is left.
    while uncovered.sum() > _LEFTOVER_FRACTION * targets.shape[0] and len(chosen) < max_spheres:
        gain = covers @ uncovered.astype(np.float32)
        best = int(np.argmax(gain))
        if gain[best] < 0.5:
            # Cannot happen for targets inside the hull (each lies in the ball of its nearest
            # candidate once the protrusion exceeds the sampling gap); be safe anyway.
            far = int(np.flatnonzero(uncovered)[0])
            candidates = np.vstack([candidates, targets[far]])
            candidate_radii = np.append(candidate_radii, 1e-6)
            covers = np.vstack([covers, (np.sum((targets - targets[far]) ** 2, axis=1) <= 1e-12).astype(np.float32)])
            best = candidates.shape[0] - 1
        chosen.append(best)
        uncovered &= covers[best] < 0.5
    return candidates[chosen].copy(), candidate_radii[chosen].copy()


def _exact_radii(equations: FloatArray, centers: FloatArray, radii: FloatArray) -> FloatArray:
    """Radii that make the balls cover the whole hull given by `equations`, not just samples of it.

    The power (Laguerre) cells of the balls partition the hull, and a point of the hull that lies
    in any ball lies in the ball of its power cell. So growing each radius to the farthest vertex
    of (power cell ∩ hull) from the center covers the hull exactly, and changes nothing (up to
    rounding) where the balls already cover their cells.
    """
    out = radii.copy()
    k = centers.shape[0]
    if k == 1:
        hull_vertices = HalfspaceIntersection(equations, _interior_point(equations, centers[0])).intersections
        out[0] = float(np.sqrt(np.max(np.sum((hull_vertices - centers[0]) ** 2, axis=1))))
        return out
    for i in range(k):
        others = np.delete(np.arange(k), i)
        # power_i(x) <= power_j(x):  2 (c_j - c_i) . x - (|c_j|^2 - r_j^2 - |c_i|^2 + r_i^2) <= 0
        lhs = 2.0 * (centers[others] - centers[i])
        rhs = (np.sum(centers[others] ** 2, axis=1) - radii[others] ** 2) - (centers[i] @ centers[i] - radii[i] ** 2)
        halfspaces = np.vstack([equations, np.column_stack([lhs, -rhs])])
        interior = _interior_point(halfspaces, centers[i])
        if interior is None:
            continue  # empty or flat cell: the other balls already cover it
        cell = HalfspaceIntersection(halfspaces, interior).intersections
        out[i] = max(out[i], float(np.sqrt(np.max(np.sum((cell - centers[i]) ** 2, axis=1)))))
    return out


def _interior_point(halfspaces: FloatArray, guess: FloatArray) -> FloatArray | None:
    """A point strictly inside {x: A x + b <= 0}: `guess` if clearly inside, else the Chebyshev center."""
    normals, offsets = halfspaces[:, :3], halfspaces[:, 3]
    norms = np.linalg.norm(normals, axis=1)
    if np.all((normals @ guess + offsets) / norms < -1e-6):
        return guess
    # maximise t subject to A x + t |A| <= -b
    result = linprog(np.array([0.0, 0.0, 0.0, -1.0]), A_ub=np.column_stack([normals, norms]), b_ub=-offsets,
                     bounds=[(None, None)] * 3 + [(0, None)], method="highs")
    if not result.success or result.x[3] < 1e-7:
        return None
    return result.x[:3]


def _volume_samples(equations: FloatArray, vertices: FloatArray, count: int, rng: np.random.Generator) -> FloatArray:
    """About `count` points uniform in the hull (rejection sampling in its bounding box).

    The covers are built from these samples; `_fan_volume_samples` draws the same distribution
    faster, but other samples would give every robot other covers (and other benchmark figures)."""
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    out: list[FloatArray] = []
    have = 0
    while have < count:
        cand = rng.uniform(low, high, size=(2 * count - have, 3))
        inside = cand[np.all(cand @ equations[:, :3].T + equations[:, 3] <= 0, axis=1)]
        out.append(inside)
        have += inside.shape[0]
    return np.vstack(out)[:count]


def _fan_volume_samples(points: FloatArray, hull: ConvexHull, count: int, rng: np.random.Generator) -> FloatArray:
    """`count` points uniform in the hull: tetrahedra fanned from an interior point to the hull's
    triangles, picked by volume, each sampled with flat Dirichlet weights. For the coverage
    check's many samples, where rejection (a dot product per facet and candidate) took most of
    a robot's sphere model build (20 of 23 s for the UR5's meshes on a loaded 2-core machine)."""
    tri = points[hull.simplices]
    apex = points[hull.vertices].mean(axis=0)
    volume = np.abs(np.einsum("ij,ij->i", tri[:, 0] - apex, np.cross(tri[:, 1] - apex, tri[:, 2] - apex))) / 6.0
    which = rng.choice(len(tri), size=count, p=volume / volume.sum())
    weights = -np.log(rng.uniform(size=(count, 4)) + 1e-300)
    weights /= weights.sum(axis=1, keepdims=True)
    return weights[:, :1] * apex + np.einsum("nk,nkj->nj", weights[:, 1:], tri[which])


def _surface_samples(points: FloatArray, hull: ConvexHull, count: int, rng: np.random.Generator) -> FloatArray:
    """About `count` points uniform on the hull's surface (area-weighted triangles), plus its vertices."""
    tri = points[hull.simplices]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    which = rng.choice(len(tri), size=count, p=area / area.sum())
    u, v = rng.uniform(size=(2, count))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    t = tri[which]
    return np.vstack([t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0]), points])


def _check_coverage(equations: FloatArray, vertices: FloatArray, points: FloatArray, hull: ConvexHull,
                    centers: FloatArray, radii: FloatArray, rng: np.random.Generator) -> None:
    samples = np.vstack([_surface_samples(points, hull, _CHECK_SAMPLES, rng),
                         _fan_volume_samples(points, hull, _CHECK_SAMPLES, rng)])
    excess = np.min(np.linalg.norm(samples[:, None, :] - centers[None], axis=2) - radii[None], axis=1)
    worst = float(excess.max())
    if worst > 1e-9:
        raise ValueError(f"sphere cover misses a hull sample by {worst:.3g} m (cover construction bug)")


def _union_volume(centers: FloatArray, radii: FloatArray, rng: np.random.Generator, count: int = 20000) -> float:
    low = (centers - radii[:, None]).min(axis=0)
    high = (centers + radii[:, None]).max(axis=0)
    cand = rng.uniform(low, high, size=(count, 3))
    inside = np.any(np.sum((cand[:, None, :] - centers[None]) ** 2, axis=2) <= radii[None] ** 2, axis=1)
    return float(np.prod(high - low) * inside.mean())


def _fibonacci_directions(count: int) -> FloatArray:
    i = np.arange(count) + 0.5
    polar = np.arccos(1 - 2 * i / count)
    azimuth = math.pi * (1 + 5**0.5) * i
    return np.column_stack([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)])


def world_radii(shapes: Sequence[LinkShape], model: RobotSphereModel, growth_m: FloatArray,
                 padding_m: float) -> FloatArray:
    """Radii with which each shape's spheres cover its PADDED hull (`grow_hull`, what FCL checks
    against the world): each sphere grows by what its own part of the grown hull needs (between
    the padding and the hull's worst growth `growth_m`), not all by the worst."""
    radii = np.array(model.radii_m, dtype=np.float64)
    if padding_m <= 0:
        return radii
    for s, shape in enumerate(shapes):
        mine = np.flatnonzero(model.shape_index == s)
        grown, _ = grow_hull(shape.hull_vertices, shape.hull_triangles, padding_m)
        fitted = radii_covering(grown, model.centers_link_m[mine], model.radii_m[mine] + padding_m)
        uniform = model.radii_m[mine] + growth_m[s]
        # Each is a cover of the grown hull on its own (mixing them per sphere is not): keep the smaller.
        radii[mine] = fitted if np.sum(fitted**3) <= np.sum(uniform**3) else uniform
    return radii


def padded_growth_m(vertices: FloatArray, triangles: np.ndarray, padding_m: float) -> float:
    """Hausdorff distance from `grow_hull(hull, padding)` to the hull [m] (>= padding_m), via FCL."""
    if padding_m <= 0:
        return 0.0
    grown, _ = grow_hull(vertices, triangles, padding_m)
    faces = np.hstack([np.full((len(triangles), 1), 3, dtype=np.int64), triangles]).ravel()
    hull = fcl.CollisionObject(fcl.Convex(np.ascontiguousarray(vertices), len(triangles), faces), fcl.Transform())
    request = fcl.DistanceRequest()
    worst = padding_m
    point = fcl.CollisionObject(fcl.Sphere(1e-9), fcl.Transform())
    for v in grown:
        point.setTranslation(v)
        worst = max(worst, float(fcl.distance(point, hull, request, fcl.DistanceResult())))
    return worst + 1e-6
