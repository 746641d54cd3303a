"""Before perception declares itself alive: compile and run everything a first frame runs.

The map kernels (`pipeline/perception/maps/voxel_kernels.py`) compile on first use; on the
first camera frame that cost seconds while joint states and frames queued up. Here every
configured camera sees a synthetic scene (a floor and a box, the arm at home), as a depth image
with and without labels and as a cloud, each decoded from the wire as the service decodes them
(numba compiles per array type, read-only included), and each integrated twice into a map of
its own, which is then exported and clustered as the service does. The service's map is not
touched.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from robonav.pipeline.camera import CameraIntrinsics
from robonav.pipeline.perception.clusters import cluster_voxels
from robonav.pipeline.perception.maps.factory import make_occupancy_map
from robonav.pipeline.perception.maps.protocol import FrameRejected
from robonav.pipeline.perception.self_filter import SelfFilter
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.types import FloatArray
from robonav.pipeline.wire.messages import DepthImage, PointCloud
from robonav.services.config import RobonavConfig, perceived_world_from_camera
from robonav.services.perception.frames import camera_frame

log = logging.getLogger("robonav.perception")

BOX_HALF_M = 0.15
BOX_HEIGHT_M = 0.15
FLOOR_ABOVE_MIN_M = 0.1


def warm_up_perception(config: RobonavConfig, robot: RobotModel, self_filter: SelfFilter, clear_filter: SelfFilter) -> float:
    """Integrate synthetic frames of every camera of `config` into a throwaway map, through the
    service's filters; returns the time it took [s]."""
    started = time.perf_counter()
    cfg = config.perception
    scratch = make_occupancy_map(cfg)
    q = robot.home_position_rad
    low, high = np.asarray(cfg.workspace_min_m, float), np.asarray(cfg.workspace_max_m, float)
    floor_z = low[2] + FLOOR_ABOVE_MIN_M
    box_xy = 0.5 * (low[:2] + high[:2])
    integrated = 0
    for camera in config.cameras:
        camera_id, intrinsics, world_from_camera = camera.camera_id, camera.intrinsics, perceived_world_from_camera(camera)
        depth, labels = _synthetic_depth(intrinsics, world_from_camera, floor_z, box_xy, camera.far_m)
        points = _back_project(depth, intrinsics)
        messages: list[DepthImage | PointCloud] = [PointCloud(stamp=3.0, camera_id=camera_id, points=points,
                                                              intrinsics=intrinsics)]
        if cfg.clearing == "projection":  # the ray-casting map takes clouds only
            messages += [DepthImage(stamp=1.0, camera_id=camera_id, intrinsics=intrinsics, depth_m=depth, labels=labels,
                                    label_names={1: "box"}),
                         DepthImage(stamp=2.0, camera_id=camera_id, intrinsics=intrinsics, depth_m=depth)]
        for message in messages:
            decoded = type(message).from_wire(message.to_wire())
            for _ in range(2):
                try:
                    scratch.integrate(camera_frame(decoded, camera, world_from_camera, robot, q),
                                      self_filter=self_filter, clear_filter=clear_filter)
                    integrated += 1
                except FrameRejected as exc:  # e.g. a camera that sees none of the scene
                    log.warning("warm-up: camera %r: %s", camera_id, exc)
    scratch.planning_binary()
    scratch.occupied_centers_m()
    voxels = scratch.occupied_voxels()
    cluster_voxels(voxels.ijk, voxels.centers_m, cfg.resolution_m, labels=voxels.labels, method=cfg.clustering,
                   min_voxels=cfg.cluster_min_voxels)
    scratch.clear()
    elapsed = time.perf_counter() - started
    log.info("warm-up: %d frames integrated in %.1f s", integrated, elapsed)
    return elapsed


def _synthetic_depth(intrinsics: CameraIntrinsics, world_from_camera: FloatArray, floor_z: float, box_xy: FloatArray,
                     far_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) float32 depth [m] of a horizontal floor at `floor_z` with a box standing on it at
    `box_xy`, and (H, W) int32 labels (1: box, 0: floor, -1: nothing); inf beyond `far_m`."""
    u, v = np.meshgrid(np.arange(intrinsics.width), np.arange(intrinsics.height))
    rays = np.stack([(u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy, np.ones(u.shape)], -1)
    directions = rays @ world_from_camera[:3, :3].T  # depth 1 along the optical axis
    origin = world_from_camera[:3, 3]
    depth = np.full(u.shape, np.inf)
    labels = np.full(u.shape, -1, dtype=np.int32)
    for z, label in ((floor_z, 0), (floor_z + BOX_HEIGHT_M, 1)):
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (z - origin[2]) / directions[..., 2]
        hit = origin[:2] + t[..., None] * directions[..., :2]
        inside = np.all(np.abs(hit - box_xy) <= BOX_HALF_M, axis=-1) if label else np.ones(u.shape, dtype=bool)
        take = (t > 0) & (t < far_m) & inside & (t < depth)
        depth[take], labels[take] = t[take], label
    return depth.astype(np.float32), labels


def _back_project(depth: np.ndarray, intrinsics: CameraIntrinsics) -> np.ndarray:
    """(N, 3) float32 points in the optical frame of the finite pixels of `depth`."""
    v, u = np.nonzero(np.isfinite(depth))
    z = depth[v, u].astype(np.float64)
    return np.column_stack([(u - intrinsics.cx) * z / intrinsics.fx, (v - intrinsics.cy) * z / intrinsics.fy,
                            z]).astype(np.float32)
