"""The planning maps of `robonav bench plan --scene cloud|camera`: an occupancy map of a problem's obstacles.

`cloud`: the obstacles' surfaces sampled every `CLOUD_SPACING_M` and inserted in one scan from a
point above the scene, as a camera that sees every side would. The planner gets what the
perception service publishes (the inflated octree and the seen voxels) plus the seen points on
a `SURFACE_RESOLUTION_M` grid, and plans with the map's clearance and its near-goal allowance
(`pipeline/collision/surface_allowance.py`).

`camera`: the configured cameras render the scene with the arm at the problem's start, the
sim's depth-noise model corrupts each frame, and the perception core integrates them: unseen
space, occlusions and flying pixels are part of the test (`camera_map`). The crop box grows to
hold the problem's obstacles (`_holding`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from robonav.pipeline.camera import CameraConfig
from robonav.pipeline.collision.fcl_shapes import world_aabb
from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.evaluation.surface_sampling import sample_object_surfaces
from robonav.pipeline.perception.config import PerceptionConfig
from robonav.pipeline.perception.depth import points_from_depth, remove_depth_edges
from robonav.pipeline.perception.maps.factory import make_occupancy_map
from robonav.pipeline.perception.maps.octree import OccupancyMap
from robonav.pipeline.perception.maps.protocol import CameraFrame
from robonav.pipeline.perception.self_filter import perception_filters
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.sim.config import SimConfig
from robonav.pipeline.sim.noise import DepthNoiseConfig, apply_depth_noise
from robonav.pipeline.sim.world import SimWorld
from robonav.pipeline.types import FloatArray

CLOUD_SPACING_M = 0.005
"""Spacing of the synthetic surface cloud for `--scene cloud` [m]."""
CLOUD_ORIGIN_HEIGHT_M = 0.3
"""The synthetic camera sits this far above the cloud's highest point [m]."""
CAMERA_FRAMES = 3
"""Noisy frames per camera for `--scene camera` (the planner's `occupancy_min_frames`)."""
SURFACE_RESOLUTION_M = 0.005
"""Cell size of the seen points the planner keeps off near a query's start and goals [m]."""


@dataclass(frozen=True)
class CameraSetup:
    """The cameras of `--scene camera` and the depth noise of every one of them."""

    cameras: tuple[CameraConfig, ...]
    noise: DepthNoiseConfig


@dataclass(frozen=True)
class PlanningMap:
    """What a planner is given of a perceived scene."""

    octomap_binary: bytes
    """The inflated occupancy map, as published."""
    resolution_m: float
    seen_voxels_m: FloatArray
    """(N, 3) centers of the voxels seen occupied, before inflation [m]."""
    inflation_m: float
    surface_m: FloatArray
    """(M, 3) seen points inside the seen voxels [m]."""

    def apply(self, world: CollisionWorld) -> None:
        """Make this the world's map, with its clearance and the seen points as its surface."""
        world.set_octree(self.octomap_binary, self.resolution_m, self.seen_voxels_m, clearance_m=self.inflation_m,
                         surface_m=self.surface_m, surface_resolution_m=SURFACE_RESOLUTION_M)


def map_of_points(points_m: FloatArray, origin_m: FloatArray, config: PerceptionConfig) -> PlanningMap:
    """Insert `points_m` (N, 3) as one scan from `origin_m` (3,) and keep the points that ended in an
    occupied voxel (a point on a voxel the scan cleared again was not kept by the map either)."""
    occupancy = OccupancyMap(config)
    if points_m.shape[0]:
        occupancy.insert(points_m, origin_m)
    seen = np.asarray(occupancy.occupied_centers_m(), dtype=np.float64)
    res = occupancy.resolution_m
    inside = np.isin(_packed(np.floor(points_m / res)), _packed(np.floor(seen / res)))
    return PlanningMap(occupancy.planning_binary(), res, seen, config.inflation_m,
                       np.asarray(points_m, dtype=np.float64)[inside].reshape(-1, 3))


def cloud_map(objects: Sequence[SceneObject], *, seed: int, config: PerceptionConfig | None = None) -> PlanningMap:
    """The map of the objects' sampled surfaces (see the module docstring).

    Raises:
        ValueError: some surface point lies beyond the map's `max_range_m` from the origin
            (octomap would only clear along such rays, never mark their ends).
    """
    cfg = config if config is not None else PerceptionConfig()
    points = sample_object_surfaces(objects, spacing_m=CLOUD_SPACING_M, rng=np.random.default_rng(seed))
    if not points.shape[0]:
        return map_of_points(points, np.zeros(3), cfg)
    low, high = points.min(axis=0), points.max(axis=0)
    origin = np.array([0.5 * (low[0] + high[0]), 0.5 * (low[1] + high[1]), high[2] + CLOUD_ORIGIN_HEIGHT_M])
    farthest = float(np.max(np.linalg.norm(points - origin, axis=1)))
    if farthest > cfg.max_range_m:
        raise ValueError(f"scene cloud reaches {farthest:.2f} m from the synthetic camera, beyond "
                         f"perception max_range_m {cfg.max_range_m}")
    return map_of_points(points, origin, cfg)


def _packed(keys: FloatArray) -> np.ndarray:
    k = keys.astype(np.int64).reshape(-1, 3) + (1 << 20)
    return (k[:, 0] << 42) | (k[:, 1] << 21) | k[:, 2]


REACH_BOX_M = ((-1.2, -1.2, -1.0), (1.5, 1.2, 1.5))
"""Where the perception crop box of `--scene camera` may grow to hold a problem's obstacles [m]:
beyond the arm's reach (0.855 m for the Panda) with room to spare."""


def _holding(config: PerceptionConfig, objects: Sequence[SceneObject]) -> PerceptionConfig:
    """`config` with its crop box grown to hold the objects (within `REACH_BOX_M`). The packaged
    box starts at the robot's base plane, where a cell's floor is; MotionBenchMaker's tables and
    shelves stand on legs down to 0.7 m below it, and a map cropped there leaves them out: the
    arm then reaches under a table into space the map never held. A cell's crop box is set up
    to hold its workspace, so the bench's is too."""
    if not objects:
        return config
    bounds = [world_aabb(o, o.world_from_object) for o in objects]
    low = np.min([center - half for center, half in bounds], axis=0) - config.resolution_m
    high = np.max([center + half for center, half in bounds], axis=0) + config.resolution_m
    low = np.maximum(np.minimum(low, config.workspace_min_m), REACH_BOX_M[0])
    high = np.minimum(np.maximum(high, config.workspace_max_m), REACH_BOX_M[1])
    return dataclasses.replace(config, workspace_min_m=tuple(float(v) for v in low),
                               workspace_max_m=tuple(float(v) for v in high))


def camera_map(objects: Sequence[SceneObject], robot: RobotModel, cameras: Sequence[CameraConfig],
               noise: DepthNoiseConfig, q_rad: FloatArray, *, seed: int, config: PerceptionConfig | None = None,
               frames: int = CAMERA_FRAMES) -> PlanningMap:
    """The map the perception core builds from rendered, noisy depth images of `cameras`, the arm at `q_rad`.

    Each camera renders the objects once (pybullet, the arm in the picture) and `frames` noisy
    copies of that image (`apply_depth_noise`: axial noise, dropouts, flying pixels at depth
    edges, seeded) go through the perception core with its self filter, as the service would
    integrate them. What the cameras do not see (back sides, shadows) stays unknown. The
    surface is the noisy points outside the robot that fall in a seen voxel.
    """
    cfg = _holding(config if config is not None else PerceptionConfig(), objects)
    rng = np.random.default_rng(seed)
    self_filter, clear_filter = perception_filters(robot.link_hull_vertices, robot.static_link_names, cfg,
                                                   robot.config.padding_m)
    occupancy = make_occupancy_map(cfg)
    sim = SimConfig(objects=tuple(objects), follow="kinematic", gravity=False, realtime=False)
    links = robot.link_poses(q_rad)
    surface: list[FloatArray] = []
    with SimWorld(robot.config, cameras[0], sim) as world:
        world.set_joint_positions(q_rad)
        for camera in cameras:
            frame = world.render_depth(camera)
            pose = np.asarray(frame.world_from_camera, dtype=np.float64)
            for _ in range(frames):
                depth, _ = apply_depth_noise(frame.depth_m, frame.segmentation, frame.intrinsics, noise, rng)
                occupancy.integrate(CameraFrame(frame.intrinsics, pose, links, depth_m=depth),
                                    self_filter=self_filter, clear_filter=clear_filter)
                # The surface is what the map kept: flying pixels go as perception drops them.
                clean = depth.copy()
                if cfg.depth_edge_jump_m > 0:
                    remove_depth_edges(clean, frame.intrinsics.fx, min_jump_m=cfg.depth_edge_jump_m)
                points = points_from_depth(clean, frame.intrinsics, max_depth_m=camera.far_m).astype(np.float64)
                points = points @ pose[:3, :3].T + pose[:3, 3]
                surface.append(points[self_filter.outside_mask(points, links)])
    seen = np.asarray(occupancy.occupied_centers_m(), dtype=np.float64).reshape(-1, 3)
    res = occupancy.resolution_m
    points = np.vstack(surface) if surface else np.zeros((0, 3))
    inside = np.isin(_packed(np.floor(points / res)), _packed(np.floor(seen / res)))
    return PlanningMap(occupancy.planning_binary(), res, seen, cfg.inflation_m, points[inside])
