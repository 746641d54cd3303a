"""Depth images to points: pinhole back-projection and OpenGL depth-buffer linearisation.

All points are in the camera's optical frame (z forward along the view axis, x right,
y down in the image), in metres. Pixel (u, v) = (column, row) has its center at integer
coordinates, matching `CameraIntrinsics.cx/cy`.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import numpy.typing as npt

from robonav.pipeline.camera import CameraIntrinsics
from robonav.pipeline.perception.maps.voxel_kernels import zbuffer

# A z-buffer value this close to 1 is the cleared background: the tiny renderer clears to
# 1 - 1 ulp of float32, not exactly 1. With near/far = 0.1/3 m this only hides surfaces
# within ~0.1 mm of the far plane, which every consumer clips anyway.
_BACKGROUND_Z_BUFFER = 1.0 - 1e-6


def points_from_depth(
    depth_m: npt.NDArray[np.floating],
    intrinsics: CameraIntrinsics,
    *,
    min_depth_m: float = 0.0,
    max_depth_m: float = math.inf,
) -> npt.NDArray[np.float32]:
    """Back-project a depth image to a point cloud in the camera optical frame.

    Args:
        depth_m: (H, W) depth along the optical axis (z, not ray length) [m]; H, W must
            match `intrinsics`. NaN, inf and non-positive values mean "no return".
        intrinsics: Pinhole intrinsics of the image.
        min_depth_m: Pixels with depth <= this are dropped [m].
        max_depth_m: Pixels with depth >= this are dropped [m].

    Returns:
        (N, 3) float32 points (x right, y down, z forward) [m], in row-major pixel order.

    Raises:
        ValueError: the image shape does not match the intrinsics, or the depth range is invalid.
    """
    depth = np.asarray(depth_m)
    if depth.shape != (intrinsics.height, intrinsics.width):
        raise ValueError(
            f"depth_m has shape {depth.shape}, expected (height, width) = "
            f"({intrinsics.height}, {intrinsics.width}) from the intrinsics"
        )
    if math.isnan(min_depth_m) or math.isnan(max_depth_m) or not min_depth_m < max_depth_m:
        raise ValueError(f"depth range needs min_depth_m < max_depth_m, got {min_depth_m}, {max_depth_m}")
    z = depth.astype(np.float32, copy=False).ravel()
    # NaN compares False, so it is dropped; the explicit > 0 also drops zeros when min is negative.
    valid = (z > max(min_depth_m, 0.0)) & (z < max_depth_m) & np.isfinite(z)
    rays = _pixel_rays(intrinsics)
    z_valid = z[valid]
    points = np.empty((z_valid.shape[0], 3), dtype=np.float32)
    points[:, 0] = rays[0][valid] * z_valid
    points[:, 1] = rays[1][valid] * z_valid
    points[:, 2] = z_valid
    return points


@functools.lru_cache(maxsize=8)
def _pixel_rays(intrinsics: CameraIntrinsics) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """(x/z, y/z) of every pixel, flattened row-major; cached because cameras rarely change."""
    if intrinsics.width <= 0 or intrinsics.height <= 0 or intrinsics.fx <= 0 or intrinsics.fy <= 0:
        raise ValueError(f"intrinsics need positive width, height, fx and fy, got {intrinsics}")
    u = (np.arange(intrinsics.width, dtype=np.float64) - intrinsics.cx) / intrinsics.fx
    v = (np.arange(intrinsics.height, dtype=np.float64) - intrinsics.cy) / intrinsics.fy
    x_over_z = np.broadcast_to(u[None, :], (intrinsics.height, intrinsics.width)).astype(np.float32).ravel()
    y_over_z = np.broadcast_to(v[:, None], (intrinsics.height, intrinsics.width)).astype(np.float32).ravel()
    x_over_z.flags.writeable = False
    y_over_z.flags.writeable = False
    return x_over_z, y_over_z


def depth_from_opengl_buffer(
    z_buffer: npt.NDArray[np.floating], near_m: float, far_m: float
) -> npt.NDArray[np.float32]:
    """Linearise an OpenGL depth buffer (as returned by pybullet) to metric depth.

    A perspective projection stores z_buffer = far (z - near) / (z (far - near)) in [0, 1],
    which is hyperbolic in the depth z; this inverts it.

    Args:
        z_buffer: (...) depth-buffer values in [0, 1] for a projection with `near_m`, `far_m`.
        near_m: Near clipping plane of the projection [m], > 0.
        far_m: Far clipping plane of the projection [m], > near_m.

    Returns:
        (...) float32 depth along the optical axis [m]; background (buffer ~1) is +inf.

    Raises:
        ValueError: the clipping planes are invalid.
    """
    if not (0.0 < near_m < far_m and math.isfinite(far_m)):
        raise ValueError(f"depth buffer needs 0 < near_m < far_m < inf, got near_m={near_m}, far_m={far_m}")
    zb = np.asarray(z_buffer, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = far_m * near_m / (far_m - (far_m - near_m) * zb)
    return np.where(zb >= _BACKGROUND_Z_BUFFER, np.inf, depth).astype(np.float32)


def depth_from_points(points_camera: npt.ArrayLike, intrinsics: CameraIntrinsics) -> tuple[npt.NDArray[np.float32], int]:
    """Render a camera-frame cloud back into a depth image (nearest point per pixel).

    A cloud made from a depth image (`points_from_depth`) maps back onto its own pixels, so
    this recovers the image, with inf where no point landed ("no return").

    Args:
        points_camera: (N, 3) points in the optical frame [m]; NaN/inf rows are skipped.
        intrinsics: The camera the points came from.

    Returns:
        The (H, W) float32 depth image [m] and the number of points that did not land in it.
    """
    points = np.asarray(points_camera)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points_camera must have shape (N, 3), got {points.shape}")
    depth = np.full((intrinsics.height, intrinsics.width), np.inf, dtype=np.float32)
    k = intrinsics
    dropped = zbuffer(np.ascontiguousarray(points, dtype=np.float64), k.fx, k.fy, k.cx, k.cy, depth)
    return depth, int(dropped)


def remove_depth_edges(depth_m: npt.NDArray[np.float32], fx: float, *, min_jump_m: float,
                       max_slope_px: float = 4.0) -> int:
    """In place: drop (set to NaN, invalid) pixels that belong to no neighbouring surface.

    At a depth edge, time-of-flight and stereo cameras return "flying pixels" between the
    near and the far surface, which land in free space (and, at the arm's silhouette, just
    outside its self filter). Such a pixel differs in depth from every 4-neighbour, while a
    pixel on a real surface, even at its edge, has a neighbour on that same surface: a pixel
    goes when no finite neighbour is within max(`min_jump_m`, `max_slope_px` * depth / fx) of
    it. The second term keeps surfaces seen at a grazing angle, whose depth grows by about
    depth / (fx * tan(angle)) per pixel. Unlike a jump edge filter that drops both sides of
    every edge, this keeps the few pixels of a mostly hidden object. Dropped pixels become
    NaN, "invalid": no return, and no evidence of free space either.

    Args:
        depth_m: (H, W) float32 depth [m]; inf/NaN mean no return.
        fx: Focal length in pixels (of this image's resolution).
        min_jump_m: Depth difference beyond which a neighbour is on another surface [m].
        max_slope_px: Differences up to this many pixel footprints (depth / fx) are surface slope.

    Returns:
        How many pixels were dropped.
    """
    finite = np.isfinite(depth_m)
    with np.errstate(invalid="ignore"):
        threshold = np.maximum(min_jump_m, max_slope_px * depth_m / fx)
        padded = np.pad(depth_m, 1, constant_values=np.nan)
        near_any = np.zeros(depth_m.shape, dtype=bool)
        for neighbour in (padded[:-2, 1:-1], padded[2:, 1:-1], padded[1:-1, :-2], padded[1:-1, 2:]):
            near_any |= np.abs(neighbour - depth_m) <= threshold  # NaN and inf neighbours never match
    lonely = finite & ~near_any
    depth_m[lonely] = np.nan
    return int(lonely.sum())
