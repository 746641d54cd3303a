"""Labelled frames: body ids become stable labels, and every point keeps its pixel's label."""

from __future__ import annotations

import dataclasses

import numpy as np

from robonav.pipeline.camera import CameraConfig
from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.sim.config import SimConfig
from robonav.pipeline.sim.noise import NO_LABEL, DepthNoiseConfig
from robonav.pipeline.sim.sensor import label_image, labelled_cloud, sensor_frame
from robonav.pipeline.sim.world import SimWorld
from robonav.pipeline.transforms import look_at_quat_xyzw, transform_points

EYE_M = (1.6, 0.2, 1.0)
CAMERA = CameraConfig(width=160, height=120, position_m=EYE_M, quat_xyzw=tuple(look_at_quat_xyzw(EYE_M, (0.6, 0.0, 0.3))))
BOX = SceneObject("box", "box", (0.8, 0.3, 0.4), quat_xyzw=(0.0, 0.0, 0.2, 1.0), size_m=(0.2, 0.3, 0.4))


def test_label_image_maps_bodies_and_leaves_the_rest_unlabelled() -> None:
    segmentation = np.array([[-1, 0, 4], [7, 4, 0]])
    labels = label_image(segmentation, {0: 0, 4: 9})
    np.testing.assert_array_equal(labels, [[NO_LABEL, 0, 9], [NO_LABEL, 9, 0]])
    assert labels.dtype == np.int32


def test_cloud_labels_follow_their_points() -> None:
    with SimWorld(RobotConfig(), CAMERA, SimConfig(objects=(BOX,), follow="kinematic")) as world:
        body_of = {name: body for body, name in world.body_labels().items()}
        rendered = world.render_depth()
    frame = sensor_frame(rendered, {body_of["robot"]: 0, body_of["box"]: 1}, DepthNoiseConfig(), np.random.default_rng(0))
    points, labels = labelled_cloud(frame, max_depth_m=CAMERA.far_m)
    assert points.shape == (labels.shape[0], 3)
    assert set(np.unique(labels).tolist()) == {0, 1}
    box_points = transform_points(np.linalg.inv(BOX.world_from_object),
                                  transform_points(CAMERA.world_from_camera, points[labels == 1]))
    # Every point labelled "box" lies on the box's surface (within the tiny renderer's depth precision).
    outside = np.abs(box_points) - np.asarray(BOX.size_m) / 2.0
    assert np.all(np.abs(outside.max(axis=1)) < 0.01)
    # The robot's points are near the base, the box's are not.
    robot_world = transform_points(CAMERA.world_from_camera, points[labels == 0])
    assert np.linalg.norm(robot_world[:, :2], axis=1).max() < 0.9


def test_noise_drops_labels_of_dropped_pixels_and_clouds_shrink() -> None:
    with SimWorld(RobotConfig(), CAMERA, SimConfig(objects=(BOX,), follow="kinematic")) as world:
        rendered = world.render_depth()
    bodies = {int(b): 1 for b in np.unique(rendered.segmentation) if b >= 0}
    clean = sensor_frame(rendered, bodies, DepthNoiseConfig(), np.random.default_rng(0))
    noisy_config = DepthNoiseConfig(enabled=True, dropout_probability=0.3)
    noisy = sensor_frame(rendered, bodies, noisy_config, noisy_config.frame_rng(0, 1))
    clean_points, _ = labelled_cloud(clean, max_depth_m=CAMERA.far_m)
    noisy_points, noisy_labels = labelled_cloud(noisy, max_depth_m=CAMERA.far_m)
    assert 0.6 * len(clean_points) < len(noisy_points) < 0.8 * len(clean_points)
    assert np.all(noisy.labels[~np.isfinite(noisy.depth_m)] == NO_LABEL)
    assert len(noisy_labels) == len(noisy_points)
    far_camera = dataclasses.replace(CAMERA, far_m=1.2)  # everything beyond is cut from the cloud
    near_points, _ = labelled_cloud(clean, max_depth_m=far_camera.far_m)
    assert len(near_points) < len(clean_points) and np.all(near_points[:, 2] < 1.2)
