"""Remove the robot's own points from a cloud using padded convex hulls of its links.

Each link is approximated by the convex hull of its shape's vertices (in the link frame),
computed once with open3d, and stored as outward half-spaces `n . x <= d`. Padding moves
every plane outward by `padding_m`. At query time the planes are applied in the link frame,
so only the link poses change per cloud.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import open3d as o3d

from robonav.pipeline.perception.config import PerceptionConfig
from robonav.pipeline.perception.filtering import validate_points, validate_transform
from robonav.pipeline.types import BoolArray, FloatArray


@dataclass(frozen=True)
class _LinkHull:
    normals_link: FloatArray
    """(P, 3) outward unit normals of the hull's distinct face planes, link frame."""
    offsets_m: FloatArray
    """(P,) plane offsets including padding: a point x is inside iff normals @ x <= offsets."""
    center_link_m: FloatArray
    """(3,) center of the bounding sphere, link frame [m]."""
    radius_m: float
    """Bounding-sphere radius including padding [m]."""


class SelfFilter:
    """Padded convex-hull model of the robot's links, for dropping points on the robot.

    The padded hull is the intersection of the hull's half-spaces pushed out by `padding_m`
    and a bounding sphere of radius (farthest vertex + padding_m). That set contains the
    exact Minkowski sum hull (+) ball(padding_m), so every point within `padding_m` of a
    link's hull is removed; it overshoots only a little near sharp hull corners.
    """

    def __init__(self, link_hull_vertices: Mapping[str, npt.ArrayLike], padding_m: float,
                 link_padding_m: Mapping[str, float] | None = None) -> None:
        """Precompute the padded half-spaces of every link.

        Args:
            link_hull_vertices: Link name -> (H, 3) vertices of its collision or visual shape
                in the link frame [m], H >= 4 and not all coplanar (flat sets are joggled).
            padding_m: Outward growth of every hull [m], >= 0.
            link_padding_m: Link name -> its own growth instead of `padding_m` [m], >= 0.

        Raises:
            ValueError: a padding is negative/non-finite, a link_padding_m name is not a link,
                or a link's vertices are malformed or too few to span a hull.
        """
        paddings = dict(link_padding_m or {})
        for name, value in {"padding_m": padding_m, **paddings}.items():
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"padding of {name} must be a finite number >= 0, got {value}")
        unknown = sorted(set(paddings) - set(link_hull_vertices))
        if unknown:
            raise ValueError(f"link_padding_m names links without a hull: {unknown}")
        self._padding_m = float(padding_m)
        self._hulls: dict[str, _LinkHull] = {
            name: _padded_hull(name, validate_points(vertices, f"link_hull_vertices[{name!r}]"),
                               float(paddings.get(name, self._padding_m)))
            for name, vertices in link_hull_vertices.items()
        }

    @property
    def link_names(self) -> tuple[str, ...]:
        """Names of the links this filter models, in construction order."""
        return tuple(self._hulls)

    @property
    def padding_m(self) -> float:
        """Outward growth of every hull without a padding of its own [m]."""
        return self._padding_m

    def bounds_m(self, world_from_link: Mapping[str, npt.ArrayLike]) -> tuple[FloatArray, FloatArray]:
        """World-frame box (lower, upper) [m] containing every padded link at these poses."""
        lows, highs = [], []
        for name, hull in self._hulls.items():
            if name not in world_from_link:
                continue
            pose = np.asarray(world_from_link[name], dtype=np.float64)
            center = pose[:3, :3] @ hull.center_link_m + pose[:3, 3]
            lows.append(center - hull.radius_m)
            highs.append(center + hull.radius_m)
        if not lows:
            return np.zeros(3), np.zeros(3) - 1.0  # empty box
        return np.min(lows, axis=0), np.max(highs, axis=0)

    def outside_mask(self, points_world: npt.ArrayLike, world_from_link: Mapping[str, npt.ArrayLike]) -> BoolArray:
        """Mask of points outside every padded link hull.

        Args:
            points_world: (N, 3) finite points in the world frame [m].
            world_from_link: Link name -> (4, 4) pose of that link in the world frame. Links
                this filter models but that are missing here are skipped (not filtered);
                extra names are ignored.

        Returns:
            (N,) bool, True for points to keep (not on the robot).
        """
        pts = validate_points(points_world, "points_world")
        outside = np.ones(pts.shape[0], dtype=bool)
        for name, hull in self._hulls.items():
            if name not in world_from_link:
                continue
            pose = validate_transform(world_from_link[name], f"world_from_link[{name!r}]")
            rotation, translation = pose[:3, :3], pose[:3, 3]
            # Cheap sphere test first: most of the scene is far from any given link.
            center_world = rotation @ hull.center_link_m + translation
            delta = pts - center_world
            near = np.flatnonzero(np.einsum("ij,ij->i", delta, delta) <= hull.radius_m * hull.radius_m)
            if near.size == 0:
                continue
            # Row-vector form of link_from_world applied to the candidate points.
            near_link = (pts[near] - translation) @ rotation
            inside = (near_link @ hull.normals_link.T <= hull.offsets_m).all(axis=1)
            outside[near[inside]] = False
        return outside


def _padded_hull(name: str, vertices_link: FloatArray, padding_m: float) -> _LinkHull:
    if vertices_link.shape[0] < 4:
        raise ValueError(
            f"link_hull_vertices[{name!r}] needs at least 4 vertices for a 3-D hull, got {vertices_link.shape[0]}"
        )
    # open3d's vector wrapper needs a writeable buffer; the robot model hands out read-only arrays.
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(vertices_link, dtype=np.float64)))
    try:
        mesh, _ = cloud.compute_convex_hull()
    except RuntimeError:
        # Flat shapes (plates, planar meshes) are degenerate for qhull; joggling gives a
        # hull of negligible thickness, which the padding then grows to a usable slab.
        mesh, _ = cloud.compute_convex_hull(joggle_inputs=True)
    hull_vertices = np.asarray(mesh.vertices, dtype=np.float64)
    triangles = np.asarray(mesh.triangles, dtype=np.int64)
    a, b, c = (hull_vertices[triangles[:, i]] for i in range(3))
    normals = np.cross(b - a, c - a)
    lengths = np.linalg.norm(normals, axis=1)
    keep = lengths > 1e-15
    normals = normals[keep] / lengths[keep, None]
    a = a[keep]
    # qhull's triangle winding is not a documented contract, so orient every normal away
    # from the vertex centroid, which lies strictly inside a 3-D hull.
    interior = hull_vertices.mean(axis=0)
    flip = np.einsum("ij,ij->i", normals, a - interior) < 0
    normals[flip] *= -1.0
    offsets = np.einsum("ij,ij->i", normals, a)
    # Coplanar faces are split into several triangles; keep each plane once.
    planes = np.unique(np.round(np.column_stack([normals, offsets]), 9), axis=0)
    lo, hi = vertices_link.min(axis=0), vertices_link.max(axis=0)
    center = 0.5 * (lo + hi)
    radius = float(np.linalg.norm(vertices_link - center, axis=1).max()) + padding_m
    return _LinkHull(
        normals_link=planes[:, :3].copy(),
        offsets_m=planes[:, 3] + padding_m,
        center_link_m=center,
        radius_m=radius,
    )


def perception_filters(link_hull_vertices: Mapping[str, npt.ArrayLike], static_links: Iterable[str],
                       config: PerceptionConfig, robot_padding_m: float) -> tuple[SelfFilter, SelfFilter]:
    """The self filter (drops the robot's points) and the clear filter (frees map voxels on the
    robot), with `config`'s paddings for moving links and at least the planner's reach for links
    no planning joint moves (the base).

    That reach is the robot padding plus the half diagonal of a voxel inflated by
    `config.inflation_m`. A point or voxel within it of the base would make every plan from
    every start START_IN_COLLISION (the base cannot move away from it) and protects nothing the
    base does not already cover. Depth noise at the base's silhouette puts such voxels there:
    over half of the goals a 1,000-scene campaign left stuck on START_IN_COLLISION named the
    base. Moving links keep the config's paddings: a motion passing an obstacle must not erase it.

    Args:
        link_hull_vertices: Link name -> (H, 3) hull vertices in the link frame [m].
        static_links: Links rigidly attached to the base (`RobotModel.static_link_names`).
        config: Filter paddings, map resolution and inflation.
        robot_padding_m: The planner's padding of the robot's links [m].
    """
    reach_m = robot_padding_m + math.sqrt(3.0) * (0.5 * config.resolution_m + config.inflation_m)
    static = tuple(static_links)

    def grown(padding_m: float) -> SelfFilter:
        return SelfFilter(link_hull_vertices, padding_m, {name: max(padding_m, reach_m) for name in static})
    return grown(config.self_filter_padding_m), grown(config.self_clear_padding_m)
