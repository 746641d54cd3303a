"""Point-cloud filters: non-finite removal, range limit, crop box and voxel downsampling.

Every function takes and returns (N, 3) float64 arrays of points in metres; the frame is
whatever the caller's array is in and is named in the argument (`points_camera`,
`points_world`). Masks are (N,) bool arrays, True for points to keep.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
import open3d as o3d

from robonav.pipeline.types import BoolArray, FloatArray


def validate_points(points: npt.ArrayLike, name: str, *, allow_non_finite: bool = False) -> FloatArray:
    """Return `points` as a C-contiguous (N, 3) float64 array, or raise.

    Args:
        points: (N, 3) array-like of points [m]; N may be 0.
        name: Name of the quantity, used in the error message (e.g. "points_world").
        allow_non_finite: Accept NaN/inf entries (only the filter that drops them does).

    Raises:
        ValueError: the array is not (N, 3), or holds NaN/inf and `allow_non_finite` is False.
    """
    arr = np.ascontiguousarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {arr.shape}")
    if not allow_non_finite and not np.isfinite(arr).all():
        raise ValueError(f"{name} contains NaN or inf values")
    return arr


def validate_transform(transform: npt.ArrayLike, name: str) -> FloatArray:
    """Return `transform` as a finite (4, 4) float64 homogeneous matrix, or raise ValueError naming it."""
    arr = np.asarray(transform, dtype=np.float64)
    if arr.shape != (4, 4):
        raise ValueError(f"{name} must have shape (4, 4), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} contains NaN or inf values")
    return arr


def finite_points(points: npt.ArrayLike) -> tuple[FloatArray, int]:
    """Drop rows holding NaN or inf (depth cameras mark missing returns that way).

    Args:
        points: (N, 3) points in any frame [m].

    Returns:
        The (M, 3) finite rows, in input order, and the number of dropped rows N - M.

    Raises:
        ValueError: `points` is not (N, 3).
    """
    arr = validate_points(points, "points", allow_non_finite=True)
    if np.isfinite(arr).all():
        return arr, 0
    # Per-column tests and np.compress: ~5x faster than isfinite(...).all(axis=1) and
    # boolean fancy indexing on (N, 3) arrays, which matters for 300k-point frames.
    keep = np.isfinite(arr[:, 0]) & np.isfinite(arr[:, 1]) & np.isfinite(arr[:, 2])
    return np.compress(keep, arr, axis=0), int(arr.shape[0] - np.count_nonzero(keep))


def range_mask(points_camera: npt.ArrayLike, max_range_m: float) -> BoolArray:
    """Mask of points no farther than `max_range_m` from the camera origin.

    Args:
        points_camera: (N, 3) finite points in the camera frame [m].
        max_range_m: Largest kept Euclidean distance from the camera origin [m], > 0.

    Returns:
        (N,) bool, True where |p| <= max_range_m.
    """
    pts = validate_points(points_camera, "points_camera")
    if not (np.isfinite(max_range_m) and max_range_m > 0):
        raise ValueError(f"max_range_m must be a finite number > 0, got {max_range_m}")
    # Compare squared distances: avoids a sqrt per point.
    return np.einsum("ij,ij->i", pts, pts) <= max_range_m * max_range_m


def crop_box_mask(
    points_world: npt.ArrayLike,
    min_m: Sequence[float] | FloatArray,
    max_m: Sequence[float] | FloatArray,
) -> BoolArray:
    """Mask of points inside the closed axis-aligned box [min_m, max_m].

    Args:
        points_world: (N, 3) finite points in the world frame [m].
        min_m: (3,) lower box corner in the world frame [m].
        max_m: (3,) upper box corner in the world frame [m]; each component > min_m's.

    Returns:
        (N,) bool, True for points inside the box (faces included).
    """
    pts = validate_points(points_world, "points_world")
    lo = np.asarray(min_m, dtype=np.float64)
    hi = np.asarray(max_m, dtype=np.float64)
    if lo.shape != (3,) or hi.shape != (3,) or not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        raise ValueError(
            f"crop box corners must be 3 finite numbers each, got min_m={lo.tolist()}, max_m={hi.tolist()}"
        )
    if not (lo < hi).all():
        raise ValueError(f"crop box min_m {lo.tolist()} must be < max_m {hi.tolist()} on every axis")
    # Per-axis comparisons on column views avoid (N, 3) temporaries (~4x faster).
    mask = (pts[:, 0] >= lo[0]) & (pts[:, 0] <= hi[0])
    for axis in (1, 2):
        mask &= (pts[:, axis] >= lo[axis]) & (pts[:, axis] <= hi[axis])
    return mask


def voxel_downsample(points: npt.ArrayLike, voxel_m: float) -> FloatArray:
    """Replace the points in each cubic voxel by their centroid (open3d `voxel_down_sample`).

    Args:
        points: (N, 3) finite points in any frame [m]; N may be 0.
        voxel_m: Voxel edge length [m], > 0.

    Returns:
        (M, 3) float64 centroids in the input frame, M <= N; order is open3d's, not the input's.
        open3d anchors the voxel grid half a voxel below the cloud's minimum corner, so the
        grid moves with the cloud (it is not aligned to the occupancy map's grid).
    """
    pts = validate_points(points, "points")
    if not (np.isfinite(voxel_m) and voxel_m > 0):
        raise ValueError(f"voxel_m must be a finite number > 0, got {voxel_m}")
    if pts.shape[0] == 0:
        return np.empty((0, 3), dtype=np.float64)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    # Copy: the returned view would otherwise keep the open3d cloud alive and share its buffer.
    return np.array(cloud.voxel_down_sample(voxel_m).points, dtype=np.float64)
