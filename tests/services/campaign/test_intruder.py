"""Where the moving scene's box may rest: a camera must hold all of it in view, not just show
enough of its pixels (real pybullet renders of the default cell's camera)."""

from __future__ import annotations

import numpy as np

from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.services.campaign.intruder import INTRUDER_MIN_PIXELS, IntruderPlacer
from robonav.services.config import load_config


def _box_seen_at(pixel_uv: tuple[float, float], distance_m: float) -> SceneObject:
    """A 10 cm box centred `distance_m` along the default camera's ray through `pixel_uv`."""
    camera = load_config().cameras[0]
    k = camera.intrinsics
    pose = camera.world_from_camera
    ray = pose[:3, :3] @ np.array([(pixel_uv[0] - k.cx) / k.fx, (pixel_uv[1] - k.cy) / k.fy, 1.0])
    center = pose[:3, 3] + distance_m * ray / np.linalg.norm(ray)
    return SceneObject(name="intruder", type="box", position_m=tuple(center), size_m=(0.1, 0.1, 0.1))


def test_a_box_across_the_image_edge_counts_as_unseen_however_many_pixels_show() -> None:
    cfg = load_config()
    camera = cfg.cameras[0]
    placer = IntruderPlacer(cfg, RobotModel.from_config(cfg.robot), goal_margin_m=0.05)
    try:
        home = np.asarray(cfg.robot.home_position_rad)
        across_top = _box_seen_at((camera.intrinsics.cx, -0.5), 1.2)
        in_view = _box_seen_at((camera.intrinsics.cx, camera.intrinsics.cy), 1.2)
        assert not camera.holds(across_top.bounds_corners_m) and camera.holds(in_view.bounds_corners_m)
        # The pixel count alone would take it: half the box shows in the image's top rows.
        placer._eyes.add_object(across_top)
        shown = placer._eyes.pixels_of(across_top.name, [camera])[0]
        placer._eyes.remove_object(across_top.name)
        assert shown >= INTRUDER_MIN_PIXELS
        assert placer.pixels_seen(across_top, home) == 0
        assert placer.pixels_seen(in_view, home) >= INTRUDER_MIN_PIXELS
    finally:
        placer.close()


def test_box_corners_follow_the_box_pose() -> None:
    box = SceneObject(name="b", type="box", position_m=(1.0, 2.0, 3.0), quat_xyzw=(0.0, 0.0, np.sin(np.pi / 8), np.cos(np.pi / 8)),
                      size_m=(0.2, 0.1, 0.4))
    corners = box.bounds_corners_m
    assert corners.shape == (8, 3)
    np.testing.assert_allclose(corners.mean(axis=0), [1.0, 2.0, 3.0], atol=1e-12)
    np.testing.assert_allclose(np.ptp(corners[:, 2]), 0.4, atol=1e-12)  # the turn is about z
    half_diagonal_xy = np.hypot(0.1, 0.05)
    np.testing.assert_allclose(np.linalg.norm(corners[:, :2] - [1.0, 2.0], axis=1), half_diagonal_xy, atol=1e-12)
