"""`CameraConfig.holds`: the view frustum in the optical frame convention the sim renders with."""

from __future__ import annotations

import numpy as np

from robonav.pipeline.camera import CameraConfig

CAMERA = CameraConfig(width=64, height=48, vertical_fov_deg=60.0, near_m=0.2, far_m=2.0,
                      position_m=(0.0, 0.0, 1.0), quat_xyzw=(1.0, 0.0, 0.0, 0.0))
"""Looking straight down from 1 m (optical z = world -z, image rows = world -y)."""


def _edge_ray(u: float, v: float) -> np.ndarray:
    """The world point 1 m in front of the camera seen at pixel (u, v)."""
    k = CAMERA.intrinsics
    in_camera = np.array([(u - k.cx) / k.fx, (v - k.cy) / k.fy, 1.0])
    pose = CAMERA.world_from_camera
    return pose[:3, :3] @ in_camera + pose[:3, 3]


def test_a_point_in_front_within_the_image_and_the_depth_range_is_held() -> None:
    assert CAMERA.holds([0.0, 0.0, 0.5])
    assert CAMERA.holds([[0.0, 0.0, 0.5], [0.1, -0.1, 0.2]])


def test_a_point_behind_too_near_or_too_far_is_not() -> None:
    assert not CAMERA.holds([0.0, 0.0, 1.5])   # behind the camera
    assert not CAMERA.holds([0.0, 0.0, 0.9])   # 0.1 m in front: nearer than near_m
    assert not CAMERA.holds([0.0, 0.0, -1.5])  # 2.5 m in front: beyond far_m


def test_the_image_border_is_the_outer_edge_of_the_outer_pixels() -> None:
    k = CAMERA.intrinsics
    for u, v in [(-0.5, k.cy), (k.width - 0.5, k.cy), (k.cx, -0.5), (k.cx, k.height - 0.5)]:
        inside = _edge_ray(u + 0.01 * np.sign(k.cx - u), v + 0.01 * np.sign(k.cy - v))
        outside = _edge_ray(u - 0.01 * np.sign(k.cx - u), v - 0.01 * np.sign(k.cy - v))
        assert CAMERA.holds(inside) and not CAMERA.holds(outside)


def test_one_point_out_of_view_is_enough_to_fail() -> None:
    points = [[0.0, 0.0, 0.5]] * 7 + [[5.0, 0.0, 0.5]]
    assert not CAMERA.holds(points)
