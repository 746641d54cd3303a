"""Pinhole depth camera: intrinsics, pose, and the optical frame convention.

The camera frame is the optical frame used by ROS and OpenCV: z forward along the view
axis, x right, y down in the image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

from robonav.pipeline.config import require
from robonav.pipeline.transforms import PoseSpec, make_transform
from robonav.pipeline.types import FloatArray


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics in pixels for an image of `width` x `height`."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float


@dataclass(frozen=True)
class CameraConfig:
    """One depth camera: id, image size, field of view, depth range, pose and rate."""

    camera_id: str = "cam0"
    width: int = 640
    height: int = 480
    vertical_fov_deg: float = 58.0
    near_m: float = 0.1
    far_m: float = 3.0
    position_m: tuple[float, float, float] = (1.6, 0.0, 1.0)
    """Camera origin in the world frame [m]."""
    quat_xyzw: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
    """Orientation of the optical frame in the world frame, scalar last."""
    rate_hz: float = 5.0
    output: Literal["cloud", "depth", "both"] = "cloud"
    """What the camera publishes: `camera/<id>/cloud` (points), `camera/<id>/depth` (the image) or both."""
    extrinsics_file: str | None = None
    """A hand-eye calibration result (`robonav calibrate solve` writes one): perception takes
    this camera's pose from it, while `position_m`/`quat_xyzw` stay the pose the sim renders
    from (the truth the calibration estimates). Relative to the config file's folder."""

    def __post_init__(self) -> None:
        require(self.width > 0 and self.height > 0, f"camera width/height must be > 0, got {self.width}x{self.height}")
        require(0 < self.vertical_fov_deg < 180, f"camera vertical_fov_deg must be in (0, 180), got {self.vertical_fov_deg}")
        require(0 < self.near_m < self.far_m, f"camera needs 0 < near_m < far_m, got {self.near_m}, {self.far_m}")
        require(self.rate_hz > 0, f"camera rate_hz must be > 0, got {self.rate_hz}")
        require(self.output in ("cloud", "depth", "both"),
                f"camera output must be 'cloud', 'depth' or 'both', got {self.output!r}")

    @property
    def world_from_camera(self) -> FloatArray:
        """4x4 pose of the optical frame in the world frame."""
        return make_transform(self.position_m, self.quat_xyzw)

    @property
    def intrinsics(self) -> CameraIntrinsics:
        """Square-pixel pinhole intrinsics from the vertical field of view."""
        fy = 0.5 * self.height / math.tan(math.radians(self.vertical_fov_deg) / 2.0)
        return CameraIntrinsics(self.width, self.height, fy, fy, (self.width - 1) / 2.0, (self.height - 1) / 2.0)

    def holds(self, points_m: npt.ArrayLike) -> bool:
        """Whether every point of `points_m` (N, 3, world frame) lies in the view frustum: in
        front of the camera between `near_m` and `far_m`, and projecting into the image."""
        points = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
        camera_from_world = np.linalg.inv(self.world_from_camera)
        in_camera = points @ camera_from_world[:3, :3].T + camera_from_world[:3, 3]
        z = in_camera[:, 2]
        if not np.all((z >= self.near_m) & (z <= self.far_m)):
            return False
        k = self.intrinsics
        u = k.cx + k.fx * in_camera[:, 0] / z
        v = k.cy + k.fy * in_camera[:, 1] / z
        # Pixel centres run from 0 to width - 1; a pixel covers half a pixel either side.
        return bool(np.all((u >= -0.5) & (u <= k.width - 0.5) & (v >= -0.5) & (v <= k.height - 0.5)))


@dataclass(frozen=True)
class CameraExtrinsics:
    """A calibrated camera pose, as `robonav calibrate solve` writes it (`services/config.py` reads and
    writes the file). The optical frame is OpenCV's, as in `CameraConfig`."""

    camera_id: str
    parent_frame: str
    """"world" for a fixed camera (world_from_camera), else the link it is mounted on (link_from_camera)."""
    position_m: tuple[float, float, float]
    quat_xyzw: tuple[float, float, float, float]
    method: str = ""
    reprojection_rms_px: float | None = None
    calibrated_at: str = ""

    def __post_init__(self) -> None:
        require(bool(self.camera_id), "camera_id must not be empty")
        require(bool(self.parent_frame), "parent_frame must not be empty")
        PoseSpec(self.position_m, self.quat_xyzw)  # validates the quaternion

    @property
    def parent_from_camera(self) -> FloatArray:
        return PoseSpec(self.position_m, self.quat_xyzw).matrix
