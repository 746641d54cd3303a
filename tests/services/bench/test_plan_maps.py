"""The perceived maps of `robonav bench plan`: a sampled cloud, and noisy renders of the configured cameras."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.services.bench.plan_maps import camera_map, cloud_map
from robonav.services.config import default_config_path, load_config


def _in_voxels(points: np.ndarray, centers: np.ndarray, resolution_m: float) -> np.ndarray:
    keys = {tuple(k) for k in np.floor(centers / resolution_m).astype(np.int64)}
    return np.array([tuple(k) in keys for k in np.floor(points / resolution_m).astype(np.int64)])


def _box_distance(points: np.ndarray, box: SceneObject) -> np.ndarray:
    """Unsigned distance of world points to an axis-aligned box's surface [m]."""
    q = np.abs(points - np.asarray(box.position_m)) - 0.5 * np.asarray(box.size_m)
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    return np.where(outside > 0, outside, -np.max(q, axis=1))


def test_cloud_map_carries_the_seen_voxels_inflation_and_surface(panda: RobotModel) -> None:
    box = SceneObject("crate", "box", (0.55, 0.2, 0.25), size_m=(0.16, 0.16, 0.2))
    planning_map = cloud_map([box], seed=0)
    assert planning_map.inflation_m == pytest.approx(0.02) and planning_map.resolution_m == pytest.approx(0.02)
    assert planning_map.surface_m.shape[0] > 1000
    assert np.all(_in_voxels(planning_map.surface_m, planning_map.seen_voxels_m, planning_map.resolution_m))
    assert np.max(_box_distance(planning_map.surface_m, box)) < 1e-6  # sampled on the box itself
    world = CollisionWorld(panda, padding_m=0.0)
    planning_map.apply(world)
    assert world.has_surface_allowance and world.map_clearance_m == pytest.approx(0.02)


def test_camera_map_sees_the_front_of_a_box_through_noise_and_not_the_robot() -> None:
    cfg = load_config(default_config_path())
    robot = RobotModel.from_config(cfg.robot)
    box = SceneObject("crate", "box", (0.55, 0.25, 0.2), size_m=(0.16, 0.16, 0.2))
    noise = dataclasses.replace(cfg.sim.noise, enabled=True)
    home = robot.home_position_rad
    planning_map = camera_map([box], robot, cfg.cameras, noise, home, seed=4, config=cfg.perception, frames=2)
    seen, surface = planning_map.seen_voxels_m, planning_map.surface_m
    assert seen.shape[0] > 20 and surface.shape[0] > 500
    # The faces toward the camera are seen, within the noise and a voxel.
    near_box = _box_distance(seen, box) < 0.03
    assert near_box.sum() > 20
    assert np.median(_box_distance(surface[_box_distance(surface, box) < 0.1], box)) < 0.01
    world = CollisionWorld(robot)
    planning_map.apply(world)
    with world.anchored(home[None], 1.0):
        assert not world.in_collision(home)  # the self filter kept the arm out of its own map


def test_camera_map_holds_what_stands_below_the_robots_base_plane() -> None:
    """MotionBenchMaker's tables stand on legs below the robot's base plane, where the packaged
    crop box ends: the bench grows the box to hold the scene, so the map has them."""
    cfg = load_config(default_config_path())
    robot = RobotModel.from_config(cfg.robot)
    post = SceneObject("post", "box", (0.6, -0.3, -0.1), size_m=(0.08, 0.08, 0.4))  # from z -0.3 to 0.1
    assert cfg.perception.workspace_min_m[2] > -0.2
    noise = dataclasses.replace(cfg.sim.noise, enabled=False)
    planning_map = camera_map([post], robot, cfg.cameras, noise, robot.home_position_rad, seed=1,
                              config=cfg.perception, frames=1)
    below = planning_map.seen_voxels_m[planning_map.seen_voxels_m[:, 2] < -0.1]
    assert below.shape[0] > 5 and np.median(_box_distance(below, post)) < 0.015  # voxels of the post itself
