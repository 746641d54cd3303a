"""How well an occupancy map matches the truth it was built from (simulated scenes).

Three figures, on the voxel grid of the map:

- surface coverage: of the voxels that hold a visible point of a true obstacle (from a
  noise-free render of the same view), the fraction that are occupied. A single camera
  cannot see back faces, so only what it sees counts. Reported exactly and with one voxel
  of slack (the voxel or one of its 26 neighbours occupied): a surface lying on a voxel
  boundary puts noisy returns on either side of it.
- spurious voxels: occupied voxels whose cube does not touch any true obstacle grown by
  one voxel (the slack noise is allowed).
- robot voxels: occupied voxels whose center lies inside the robot's unpadded links.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from robonav.pipeline.evaluation.surface_sampling import sample_object_surfaces
from robonav.pipeline.perception.self_filter import SelfFilter
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.types import FloatArray

_NEIGHBOURS = np.array([[i, j, k] for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)], dtype=np.int64)


@dataclass(frozen=True)
class MapAccuracy:
    """See the module docstring."""

    surface_voxels: int
    """Voxels holding a visible point of a true obstacle."""
    surface_covered: float
    """Fraction of them occupied (0..1)."""
    surface_covered_within_one_voxel: float
    """Fraction with an occupied voxel among themselves and their 26 neighbours (0..1)."""
    occupied: int
    spurious: int
    """Occupied voxels whose cube does not touch a true obstacle grown by one voxel."""
    spurious_fraction: float
    on_robot: int
    """Occupied voxels with their center inside an unpadded robot link."""


def map_accuracy(occupied_centers_m: npt.ArrayLike, resolution_m: float, *, visible_surface_m: npt.ArrayLike,
                 objects: Sequence[SceneObject], robot_hulls: Mapping[str, FloatArray],
                 world_from_link: Mapping[str, npt.ArrayLike], sample_spacing_m: float = 0.004) -> MapAccuracy:
    """Compare a map with the truth.

    Args:
        occupied_centers_m: (N, 3) occupied voxel centers, world frame [m].
        resolution_m: Voxel edge [m].
        visible_surface_m: (M, 3) points of true obstacles a noise-free camera sees [m].
        objects: The true obstacles (primitives), world frame.
        robot_hulls: Link name -> (V, 3) convex hull vertices in the link frame [m].
        world_from_link: Link poses when the map was built.
        sample_spacing_m: Spacing of the surface samples that stand for the obstacles [m].
    """
    centers = np.asarray(occupied_centers_m, dtype=np.float64).reshape(-1, 3)
    occupied_keys = _keys(centers, resolution_m)
    surface_keys = np.unique(_keys(np.asarray(visible_surface_m, dtype=np.float64).reshape(-1, 3), resolution_m), axis=0)
    occupied_set = {tuple(k) for k in occupied_keys.tolist()}
    covered = np.array([tuple(k) in occupied_set for k in surface_keys.tolist()], dtype=bool)
    near = np.array([any(tuple(k + n) in occupied_set for n in _NEIGHBOURS) for k in surface_keys], dtype=bool)

    spurious = int(np.count_nonzero(spurious_voxels(centers, resolution_m, objects, sample_spacing_m)))
    on_robot = 0
    if centers.shape[0]:
        on_robot = int(np.count_nonzero(~SelfFilter(robot_hulls, 0.0).outside_mask(centers, world_from_link)))
    n_surface = int(surface_keys.shape[0])
    return MapAccuracy(
        surface_voxels=n_surface,
        surface_covered=float(covered.mean()) if n_surface else 1.0,
        surface_covered_within_one_voxel=float(near.mean()) if n_surface else 1.0,
        occupied=int(centers.shape[0]), spurious=spurious,
        spurious_fraction=spurious / centers.shape[0] if centers.shape[0] else 0.0,
        on_robot=on_robot)


def noise_reach_m(resolution_m: float) -> float:
    """How far from an obstacle's surface a voxel center explained by it may lie [m]: a voxel
    touches the obstacle grown by one voxel when its center is within half a voxel diagonal plus
    one voxel of it."""
    return resolution_m * (0.5 * np.sqrt(3.0) + 1.0)


def spurious_voxels(centers_m: npt.ArrayLike, resolution_m: float, objects: Sequence[SceneObject],
                    sample_spacing_m: float = 0.004) -> npt.NDArray[np.bool_]:
    """Which voxels (N, 3 centers [m]) have a cube that touches no true obstacle grown by one
    voxel: what no object explains, even allowing a voxel of noise (`MapAccuracy.spurious`)."""
    centers = np.asarray(centers_m, dtype=np.float64).reshape(-1, 3)
    reach = noise_reach_m(resolution_m) + sample_spacing_m
    truth = _inside_any(centers, objects)
    if objects and not truth.all():
        samples = sample_object_surfaces(objects, spacing_m=sample_spacing_m, rng=np.random.default_rng(0))
        distance, _ = cKDTree(samples).query(centers[~truth], distance_upper_bound=reach)
        truth[~truth] = distance <= reach
    return ~truth


def below_objects(points_m: npt.ArrayLike, objects: Sequence[SceneObject], margin_m: float = 0.0) -> npt.NDArray[np.bool_]:
    """Which points (N, 3) [m] lie straight below a true object: inside the footprint of its
    world-frame bounding box grown by `margin_m` (a map's surface voxels reach past the
    surface), lower than its bottom. Perception fills such columns when `fill_below_surfaces`
    is on (it assumes what it sees rests on solid matter), so a voxel there that no object
    explains is that assumption, not noise."""
    points = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    below = np.zeros(points.shape[0], dtype=bool)
    for obj in objects:
        corners = obj.bounds_corners_m
        low, high = corners.min(axis=0) - margin_m, corners.max(axis=0) + margin_m
        below |= np.all((points[:, :2] >= low[:2]) & (points[:, :2] <= high[:2]), axis=1) & (points[:, 2] < low[2])
    return below


def _keys(points_m: FloatArray, resolution_m: float) -> npt.NDArray[np.int64]:
    return np.floor(points_m / resolution_m).astype(np.int64)


def _inside_any(points_m: FloatArray, objects: Sequence[SceneObject]) -> npt.NDArray[np.bool_]:
    """Points inside any box, sphere, cylinder or capsule (meshes count by their bounding box)."""
    inside = np.zeros(points_m.shape[0], dtype=bool)
    for obj in objects:
        pose = obj.world_from_object
        local = (points_m - pose[:3, 3]) @ pose[:3, :3]
        if obj.type == "sphere":
            inside |= np.linalg.norm(local, axis=1) <= obj.radius_m
        elif obj.type == "cylinder":
            inside |= (np.linalg.norm(local[:, :2], axis=1) <= obj.radius_m) & (np.abs(local[:, 2]) <= obj.length_m / 2)
        elif obj.type == "capsule":
            z = np.clip(local[:, 2], -obj.length_m / 2, obj.length_m / 2)
            inside |= np.linalg.norm(local - np.column_stack([np.zeros_like(z), np.zeros_like(z), z]), axis=1) <= obj.radius_m
        else:
            center, half = obj.local_bounds_m
            inside |= np.all(np.abs(local - center) <= half, axis=1)
    return inside
