"""Depth back-projection and OpenGL depth-buffer linearisation."""

from __future__ import annotations

import math
import time

import numpy as np
import pybullet as p
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robonav.pipeline.camera import CameraConfig, CameraIntrinsics
from robonav.pipeline.perception.depth import depth_from_opengl_buffer, points_from_depth

OFF_CENTRE = CameraIntrinsics(width=40, height=30, fx=50.0, fy=60.0, cx=17.0, cy=12.5)


def test_plane_at_known_depth_back_projects_with_pinhole_geometry() -> None:
    depth_m = 1.7
    points = points_from_depth(np.full((30, 40), depth_m), OFF_CENTRE)

    assert points.dtype == np.float32
    assert points.shape == (30 * 40, 3)
    np.testing.assert_allclose(points[:, 2], depth_m, rtol=1e-6)
    # x spans columns 0..W-1 and y rows 0..H-1 through the principal point.
    assert points[:, 0].min() == pytest.approx((0 - 17.0) / 50.0 * depth_m, rel=1e-5)
    assert points[:, 0].max() == pytest.approx((39 - 17.0) / 50.0 * depth_m, rel=1e-5)
    assert points[:, 1].min() == pytest.approx((0 - 12.5) / 60.0 * depth_m, rel=1e-5)
    assert points[:, 1].max() == pytest.approx((29 - 12.5) / 60.0 * depth_m, rel=1e-5)
    # Row-major order: pixel (u=5, v=3) is point 3 * W + 5; y grows downwards in the image.
    np.testing.assert_allclose(points[3 * 40 + 5], [(5 - 17.0) / 50.0 * depth_m, (3 - 12.5) / 60.0 * depth_m, depth_m],
                               rtol=1e-5)


def test_every_point_reprojects_to_its_pixel() -> None:
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.2, 3.0, size=(30, 40))
    points = points_from_depth(depth, OFF_CENTRE).astype(np.float64)
    u = OFF_CENTRE.fx * points[:, 0] / points[:, 2] + OFF_CENTRE.cx
    v = OFF_CENTRE.fy * points[:, 1] / points[:, 2] + OFF_CENTRE.cy
    vv, uu = np.mgrid[0:30, 0:40]
    np.testing.assert_allclose(u, uu.ravel(), atol=1e-3)
    np.testing.assert_allclose(v, vv.ravel(), atol=1e-3)
    np.testing.assert_allclose(points[:, 2], depth.ravel(), rtol=1e-6)


def test_invalid_and_out_of_range_pixels_are_dropped() -> None:
    depth = np.full((30, 40), 1.0)
    depth[0, 0] = np.nan
    depth[0, 1] = 0.0
    depth[0, 2] = np.inf
    depth[0, 3] = -np.inf
    depth[0, 4] = -1.0
    depth[1, 0] = 0.3  # <= min
    depth[1, 1] = 2.5  # >= max
    depth[1, 2] = 2.0  # exactly max: dropped

    points = points_from_depth(depth, OFF_CENTRE, min_depth_m=0.3, max_depth_m=2.0)

    assert points.shape == (30 * 40 - 8, 3)
    assert np.all(np.isfinite(points))
    np.testing.assert_allclose(points[:, 2], 1.0)


def test_all_invalid_gives_empty_cloud() -> None:
    points = points_from_depth(np.full((30, 40), np.inf, dtype=np.float32), OFF_CENTRE)
    assert points.shape == (0, 3)
    assert points.dtype == np.float32


def test_bad_inputs_raise_value_error() -> None:
    with pytest.raises(ValueError, match="depth_m has shape"):
        points_from_depth(np.ones((40, 30)), OFF_CENTRE)
    with pytest.raises(ValueError, match="min_depth_m < max_depth_m"):
        points_from_depth(np.ones((30, 40)), OFF_CENTRE, min_depth_m=2.0, max_depth_m=1.0)
    with pytest.raises(ValueError, match="near_m"):
        depth_from_opengl_buffer(np.zeros(3), near_m=0.0, far_m=1.0)
    with pytest.raises(ValueError, match="far_m"):
        depth_from_opengl_buffer(np.zeros(3), near_m=2.0, far_m=1.0)


def test_vga_frame_is_fast() -> None:
    cam = CameraConfig()
    depth = np.random.default_rng(1).uniform(0.2, 3.0, size=(cam.height, cam.width)).astype(np.float32)
    depth[::7] = np.inf
    points_from_depth(depth, cam.intrinsics)  # warm the ray cache
    best_s = math.inf
    for _ in range(5):
        start = time.perf_counter()
        points_from_depth(depth, cam.intrinsics)
        best_s = min(best_s, time.perf_counter() - start)
    # A few ms on a laptop; the bound is loose so loaded CI machines pass.
    assert best_s < 0.05


def _z_buffer(depth_m: np.ndarray, near_m: float, far_m: float) -> np.ndarray:
    """Depth-buffer value pybullet writes for a point at depth_m, using pybullet's own projection."""
    proj = np.array(p.computeProjectionMatrixFOV(60.0, 1.0, near_m, far_m), dtype=np.float64).reshape(4, 4).T
    z_eye = -np.asarray(depth_m, dtype=np.float64)  # OpenGL eye space looks along -z
    clip_z = proj[2, 2] * z_eye + proj[2, 3]
    clip_w = proj[3, 2] * z_eye
    return (clip_z / clip_w + 1.0) / 2.0


@settings(max_examples=200, deadline=None)
@given(
    near_m=st.floats(0.01, 1.0),
    far_over_near=st.floats(1.5, 200.0),
    fraction=st.floats(0.0, 0.99),
)
def test_linearisation_round_trips_known_depth(near_m: float, far_over_near: float, fraction: float) -> None:
    far_m = near_m * far_over_near
    depth_m = near_m + fraction * (far_m - near_m)
    z_buffer = _z_buffer(np.array([depth_m]), near_m, far_m)
    # pybullet's matrices are float32, hence the tolerance.
    np.testing.assert_allclose(depth_from_opengl_buffer(z_buffer, near_m, far_m), [depth_m], rtol=1e-4)


def test_linearisation_known_values_and_background() -> None:
    near_m, far_m = 0.1, 3.0
    z_buffer = np.array([[0.0, 1.0], [np.float32(1.0) - np.finfo(np.float32).eps / 2, 0.91954023]], dtype=np.float32)
    depth = depth_from_opengl_buffer(z_buffer, near_m, far_m)
    assert depth.dtype == np.float32
    assert depth.shape == (2, 2)
    assert depth[0, 0] == pytest.approx(near_m)
    assert depth[0, 1] == math.inf
    assert depth[1, 0] == math.inf  # the tiny renderer clears to 1 - 1 ulp
    assert depth[1, 1] == pytest.approx(0.9, abs=1e-5)


def test_the_flying_pixel_filter_drops_pixels_between_surfaces_and_keeps_the_surfaces() -> None:
    from robonav.pipeline.perception.depth import remove_depth_edges

    fx = 554.0
    rows, cols = np.mgrid[0:120, 0:160]
    depth = (1.5 + 0.004 * rows).astype(np.float32)  # a floor seen at a grazing angle: 4 mm per row
    depth[40:80, 60:100] = 1.0  # a box in front of it
    depth[39, 60:100] = np.where(np.arange(40) % 2 == 0, 1.1, 1.3)  # flying pixels along its top edge
    depth[60, 59] = 1.0  # a two-pixel sliver of the box poking out: a real surface, however small
    depth[0:5, 0:5] = np.inf  # no return
    kept_box, kept_floor = depth[40:80, 60:100].copy(), depth[90:, :].copy()
    dropped = remove_depth_edges(depth, fx, min_jump_m=0.02)
    assert dropped == 40 and np.isnan(depth[39, 60:100]).all()  # every flying pixel, nothing else
    np.testing.assert_array_equal(depth[40:80, 60:100], kept_box)  # the box, its edges included
    np.testing.assert_array_equal(depth[90:, :], kept_floor)  # the grazing floor
    assert depth[60, 59] == 1.0 and np.isinf(depth[0:5, 0:5]).all()
