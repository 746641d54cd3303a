"""Probabilistic occupancy map (an octomap OcTree) and its inflated planning snapshot.

Voxels are addressed by integer grid keys `k = floor(p / resolution)` per axis, the same
grid octomap uses (octomap's own keys add a constant 2**15 offset); a voxel's center is
`(k + 0.5) * resolution`. All coordinates are in the world frame, in metres.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np
import numpy.typing as npt
import octomap
import open3d as o3d

from robonav.pipeline.perception.cloud_pipeline import process_cloud_with_clearing
from robonav.pipeline.perception.config import PerceptionConfig
from robonav.pipeline.perception.filtering import validate_points
from robonav.pipeline.perception.maps.protocol import CameraFrame, FrameRejected, OccupiedVoxels
from robonav.pipeline.perception.self_filter import SelfFilter
from robonav.pipeline.types import BoolArray, FloatArray

# Integer keys are packed into one int64 for fast set operations; 21 bits per axis covers
# octomap's 16-bit key range plus any inflation radius.
_KEY_BIAS = 1 << 20
_KEY_BITS = 21


class OccupancyMap:
    """Occupancy octree fed by depth clouds; free-space ray casting lets vanished objects clear.

    Each `insert` marks the voxels holding the points as hits (`prob_hit`) and every voxel
    on the rays from the sensor to them as misses (`prob_miss`), in octomap's clamped
    log-odds, each voxel at most once per insert. A voxel seen occupied until saturation
    (octomap's default clamp, probability 0.971, log-odds 3.48) needs
    ceil(3.48 / -logit(prob_miss)) misses to turn free again: 9 frames with prob_miss = 0.4.
    """

    def __init__(self, config: PerceptionConfig) -> None:
        """Create an empty map with `config.resolution_m` leaves and its hit/miss probabilities."""
        self._config = config
        self._tree = self._new_tree()
        self._occupied_cache: FloatArray | None = None

    @property
    def resolution_m(self) -> float:
        """Leaf voxel edge length [m]."""
        return self._config.resolution_m

    @property
    def voxel_count(self) -> int:
        """Number of occupied voxels at leaf resolution (pruned blocks counted per leaf)."""
        return int(self.occupied_centers_m().shape[0])

    def clear(self) -> None:
        """Forget everything: every voxel becomes unknown."""
        self._tree.clear()
        self._occupied_cache = None

    def integrate(self, frame: CameraFrame, *, self_filter: SelfFilter, clear_filter: SelfFilter) -> dict[str, float]:
        """`OccupancyBackend.integrate` for point clouds: the cloud pipeline, then `insert` with
        ray casting, then voxels on the robot freed.

        Points dropped by the crop or the self filter still clear the space their rays crossed,
        so a moved arm or object leaves no ghost where nothing is seen behind it.

        Raises:
            FrameRejected: "unsupported" for a depth image (use `perception.clearing: projection`).
        """
        if frame.points_camera_m is None:
            raise FrameRejected("unsupported", "depth images need perception.clearing: projection")
        points_world, clear_only_world, stats = process_cloud_with_clearing(
            frame.points_camera_m, world_from_camera=frame.world_from_camera, config=self._config,
            self_filter=self_filter, world_from_link=frame.world_from_link)
        t0 = time.perf_counter()
        self.insert(points_world, np.asarray(frame.world_from_camera)[:3, 3], clear_only_world=clear_only_world)
        # Voxels inside the robot are traces of the arm that its body now hides from every ray.
        self.free_where(lambda centers: ~clear_filter.outside_mask(centers, frame.world_from_link))
        return {**stats.stage_ms, "raycast": (time.perf_counter() - t0) * 1e3}

    def insert(
        self,
        points_world: npt.ArrayLike,
        sensor_origin_world: npt.ArrayLike,
        *,
        clear_only_world: npt.ArrayLike | None = None,
    ) -> None:
        """Integrate one cloud: endpoints become more occupied, voxels along the rays more free.

        Args:
            points_world: (N, 3) finite measurement endpoints in the world frame [m]; already
                cropped and self-filtered. They are marked occupied.
            sensor_origin_world: (3,) camera origin in the world frame [m], where rays start.
                Rays are clipped to `config.max_range_m`; longer ones only clear free space.
            clear_only_world: Optional (M, 3) finite measurements that must not be marked
                occupied but whose rays still show free space: points cropped away outside
                the workspace box (the floor below it), points on the robot. Without them,
                an object that left is never cleared where the camera now sees past it to
                such a surface. Each currently occupied voxel that a segment from the sensor
                to one of these points passes through (and leaves before the point) gets one
                miss per insert, unless this insert marks it occupied. Unknown and free
                voxels are left alone: the planner only sees occupied ones.
        """
        pts = validate_points(points_world, "points_world")
        origin = np.asarray(sensor_origin_world, dtype=np.float64)
        if origin.shape != (3,) or not np.isfinite(origin).all():
            raise ValueError(f"sensor_origin_world must be 3 finite numbers, got {origin.tolist()}")
        if clear_only_world is not None:
            crossed = self._crossed_keys(self.occupied_centers_m(), validate_points(clear_only_world, "clear_only_world"),
                                         origin)
            # This scan's hits win over its misses, as within one octomap insertPointCloud.
            missed = np.setdiff1d(crossed, _pack_keys(_centers_to_keys(pts, self.resolution_m)))
            if missed.size:
                # Misses before hits, as octomap orders them within one scan.
                self._tree.updateNodes(_keys_to_centers(missed, self.resolution_m), False)
                self._occupied_cache = None
        if pts.shape[0] == 0:
            return
        # discretize=True casts one ray per endpoint voxel (to its center) instead of one per
        # point: ~35% faster on downsampled depth frames, and the map cannot resolve the
        # difference. lazy_eval stays off: it skips pruning, which doubles the leaf count.
        self._tree.insertPointCloud(pts, origin, maxrange=self._config.max_range_m, discretize=True)
        self._fill_below(pts, origin)
        self._occupied_cache = None

    def _fill_below(self, points_world: FloatArray, origin: FloatArray) -> None:
        """One hit for each voxel under an endpoint's voxel, down to the workspace floor, except
        where this scan's rays pass through (the opening under a shelf board)."""
        if not self._config.fill_below_surfaces:
            return
        res = self.resolution_m
        keys = _centers_to_keys(points_world, res)
        floor_z = math.floor(self._config.workspace_min_m[2] / res)
        columns, inverse = np.unique(keys[:, :2], axis=0, return_inverse=True)
        top_z = np.full(len(columns), np.iinfo(np.int64).min)
        np.maximum.at(top_z, inverse.ravel(), keys[:, 2])
        heights = np.maximum(top_z - floor_z, 0)  # voxels strictly below each column's top
        if heights.sum() == 0:
            return
        column_of = np.repeat(np.arange(len(columns)), heights)
        # Position within each column: 0 .. height-1 counted down from the top.
        starts = np.repeat(np.cumsum(heights) - heights, heights)
        depth = np.arange(heights.sum()) - starts
        filled = _pack_keys(np.column_stack([columns[column_of], top_z[column_of] - 1 - depth]))
        centers = _keys_to_centers(filled, res)
        centers = centers[~np.isin(filled, self._crossed_keys(centers, points_world, origin))]
        if centers.shape[0]:
            self._tree.updateNodes(centers, True)

    def free_where(self, inside: Callable[[FloatArray], BoolArray]) -> int:
        """Mark free every occupied voxel whose center `inside` flags; returns how many.

        For space known to be taken by something else: the robot's own links (a voxel there
        is a trace of the arm that its body now hides from the camera, so no ray can clear
        it), or objects the planner already models.

        Args:
            inside: maps (N, 3) voxel centers in the world frame [m] to an (N,) bool mask.
        """
        centers = self.occupied_centers_m()
        if centers.shape[0] == 0:
            return 0
        mask = np.asarray(inside(centers), dtype=bool)
        if mask.shape != (centers.shape[0],):
            raise ValueError(f"inside() must return one bool per center, got shape {mask.shape}")
        hidden = centers[mask]
        if hidden.shape[0]:
            # One clamped-minimum update frees a voxel at once, however saturated it was.
            for center in hidden:
                self._tree.updateNode(center, float(self._tree.getClampingThresMinLog()) - 10.0)
            self._occupied_cache = None
        return int(hidden.shape[0])

    def _crossed_keys(self, centers: FloatArray, points_world: FloatArray, origin: FloatArray) -> npt.NDArray[np.int64]:
        """Packed keys of the voxels at `centers` (occupied ones, or ones to fill) that
        sensor-to-point segments pass through and leave.

        octomap-python exposes no free-only ray update (nor its ray keys), so this casts the
        segments against the occupied voxels' cubes with open3d's Embree ray caster instead;
        only occupied voxels can change the planning map, which keeps the work small.
        """
        if centers.shape[0] == 0 or points_world.shape[0] == 0:
            return np.empty(0, dtype=np.int64)
        segments = points_world - origin
        length_m = np.linalg.norm(segments, axis=1)
        # Like octomap's rays, clearing stops at max range.
        too_long = length_m > self._config.max_range_m
        segments[too_long] *= (self._config.max_range_m / length_m[too_long])[:, None]
        vertices = (centers[:, None, :] + _CUBE_CORNERS[None, :, :] * (0.5 * self.resolution_m)).reshape(-1, 3)
        offsets = 8 * np.arange(centers.shape[0], dtype=np.uint32)
        triangles = (_CUBE_TRIANGLES[None, :, :] + offsets[:, None, None]).reshape(-1, 3)
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(triangles))
        # Unnormalised directions: t in [0, 1] spans the segment.
        rays = np.hstack([np.broadcast_to(origin, segments.shape), segments]).astype(np.float32)
        hits = {k: v.numpy() for k, v in scene.list_intersections(o3d.core.Tensor(rays)).items()}
        if hits["t_hit"].size == 0:
            return np.empty(0, dtype=np.int64)
        voxel = hits["primitive_ids"].astype(np.int64) // _CUBE_TRIANGLES.shape[0]
        pair = hits["ray_ids"].astype(np.int64) * centers.shape[0] + voxel
        # A segment crosses a voxel when it leaves it before its end: the last of its
        # (entry, exit) intersections with that cube has t < 1. The voxel holding the point
        # itself is not crossed, as in octomap.
        order = np.argsort(pair, kind="stable")
        pair, t_hit = pair[order], hits["t_hit"][order]
        starts = np.flatnonzero(np.r_[True, pair[1:] != pair[:-1]])
        last_t = np.maximum.reduceat(t_hit, starts)
        crossed = np.unique(pair[starts][last_t < 1.0] % centers.shape[0])
        return _pack_keys(_centers_to_keys(centers[crossed], self.resolution_m))

    def occupied_centers_m(self) -> FloatArray:
        """Centers of all occupied voxels at leaf resolution.

        Returns:
            (N, 3) float64 read-only array of voxel centers in the world frame [m], sorted by
            voxel key. Pruned coarse nodes are expanded into their leaf-size voxels.
        """
        if self._occupied_cache is None:
            centers = _keys_to_centers(np.sort(self._occupied_keys()), self.resolution_m)
            centers.setflags(write=False)
            self._occupied_cache = centers
        return self._occupied_cache

    def occupied_voxels(self) -> OccupiedVoxels:
        """The occupied voxels and their grid keys; this map keeps no labels."""
        centers = self.occupied_centers_m()
        return OccupiedVoxels(ijk=np.floor(centers / self.resolution_m).astype(np.int64), centers_m=centers, labels=None)

    def inflated_centers_m(self) -> FloatArray:
        """Occupied voxels dilated by `config.inflation_m`, as leaf-voxel centers.

        The radius is rounded up to r whole voxels. A voxel is added when its cube comes
        closer than r voxels to an occupied voxel's cube (gap measured between the cubes,
        not the centers), so the union of the inflated cubes contains every point within
        `inflation_m` of an occupied cube. r = 1 is the 26-neighbourhood.

        Returns:
            (M, 3) float64 voxel centers in the world frame [m], a superset of
            `occupied_centers_m()`, sorted by voxel key.
        """
        keys = self._occupied_keys()
        offsets = inflation_offsets(self._config.inflation_m, self.resolution_m)
        if keys.size and offsets.shape[0] > 1:
            keys = (keys[:, None] + _pack_offsets(offsets)[None, :]).ravel()
        return _keys_to_centers(np.unique(keys), self.resolution_m)

    def planning_binary(self) -> bytes:
        """Inflated occupied voxels as a complete octomap binary `.bt` file (header + data).

        Every voxel in the file is occupied (maximum-likelihood); unknown and free space are
        absent. Read it back with `octomap.OcTree(res).readBinary(data)`; `fcl.OcTree`
        wants only the part after the header's "data" line (see `pipeline/collision.py`).
        """
        tree = octomap.OcTree(self.resolution_m)
        centers = self.inflated_centers_m()
        if centers.shape[0]:
            tree.updateNodes(centers, True, lazy_eval=True)
            tree.updateInnerOccupancy()
        # writeBinary converts the tree to max-likelihood and prunes it in place, which is
        # why it is only ever called on this throwaway tree, never on the live map.
        data = tree.writeBinary()
        if not isinstance(data, bytes):
            raise RuntimeError("octomap failed to serialise the planning tree")
        return data

    def _new_tree(self) -> octomap.OcTree:
        tree = octomap.OcTree(self._config.resolution_m)
        tree.setProbHit(self._config.prob_hit)
        tree.setProbMiss(self._config.prob_miss)
        return tree

    def _occupied_keys(self) -> npt.NDArray[np.int64]:
        """Packed grid keys of occupied voxels at leaf resolution (unsorted, unique)."""
        if self._occupied_cache is not None:
            return _pack_keys(_centers_to_keys(self._occupied_cache, self.resolution_m))
        res = self.resolution_m
        leaf_centers: list[FloatArray] = []
        block_corners: dict[int, list[FloatArray]] = {}
        # octomap-python's extractPointCloud also expands pruned *free* nodes to leaves,
        # which is slow for large free volumes; iterating leaves and keeping the occupied
        # ones avoids that.
        for leaf in self._tree.begin_leafs():
            if not self._tree.isNodeOccupied(leaf):
                continue
            size = leaf.getSize()
            if size <= 1.5 * res:
                leaf_centers.append(leaf.getCoordinate())
            else:
                width = int(round(size / res))
                block_corners.setdefault(width, []).append(leaf.getCoordinate() - 0.5 * size)
        parts = [np.floor(np.array(leaf_centers).reshape(-1, 3) / res).astype(np.int64)]
        for width, corners in block_corners.items():
            # Corners of pruned blocks lie on voxel boundaries; round to absorb float32 error.
            base = np.round(np.array(corners) / res).astype(np.int64)
            steps = np.arange(width, dtype=np.int64)
            grid = np.stack(np.meshgrid(steps, steps, steps, indexing="ij"), axis=-1).reshape(-1, 3)
            parts.append((base[:, None, :] + grid[None, :, :]).reshape(-1, 3))
        return _pack_keys(np.concatenate(parts))


# Unit-cube corners (index 4x + 2y + z for x, y, z in {0, 1}, mapped to -1/+1) and its 12 triangles.
_CUBE_CORNERS = np.array([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])
_CUBE_TRIANGLES = np.array(
    [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
     [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]],
    dtype=np.uint32,
)


def inflation_offsets(inflation_m: float, resolution_m: float) -> npt.NDArray[np.int64]:
    """(K, 3) integer voxel offsets whose cube is closer than r voxels to the origin voxel."""
    # The small tolerance keeps e.g. 0.04 / 0.02 from rounding up to 3 voxels.
    r = math.ceil(inflation_m / resolution_m - 1e-9)
    if r <= 0:
        return np.zeros((1, 3), dtype=np.int64)
    steps = np.arange(-r, r + 1, dtype=np.int64)
    grid = np.stack(np.meshgrid(steps, steps, steps, indexing="ij"), axis=-1).reshape(-1, 3)
    gap = np.maximum(np.abs(grid) - 1, 0)
    return grid[(gap * gap).sum(axis=1) < r * r]


def _centers_to_keys(centers_m: FloatArray, resolution_m: float) -> npt.NDArray[np.int64]:
    return np.floor(centers_m / resolution_m).astype(np.int64)


def _keys_to_centers(packed: npt.NDArray[np.int64], resolution_m: float) -> FloatArray:
    return (_unpack_keys(packed).astype(np.float64) + 0.5) * resolution_m


def _pack_keys(keys: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    biased = keys + _KEY_BIAS
    return (biased[:, 0] << (2 * _KEY_BITS)) | (biased[:, 1] << _KEY_BITS) | biased[:, 2]


def _pack_offsets(offsets: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    # Packing is linear in each axis as long as no axis over/underflows its 21 bits,
    # so a packed offset can be added to a packed key directly.
    return (offsets[:, 0] << (2 * _KEY_BITS)) + (offsets[:, 1] << _KEY_BITS) + offsets[:, 2]


def _unpack_keys(packed: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    mask = (1 << _KEY_BITS) - 1
    fields = [(packed >> (2 * _KEY_BITS)) & mask, (packed >> _KEY_BITS) & mask, packed & mask]
    return np.column_stack(fields) - _KEY_BIAS
