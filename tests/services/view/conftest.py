"""Helpers shared by the view's tests."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from robonav.services.view.app import CAMERA_FOV_RAD, CAMERA_LOOK_AT_M, CAMERA_POSITION_M


def project(points_m: np.ndarray, width: int, height: int, eye_m: Sequence[float] = CAMERA_POSITION_M,
            target_m: Sequence[float] = CAMERA_LOOK_AT_M) -> np.ndarray:
    """Pixels (N, 2) of world points in the browser camera at `eye_m` looking at `target_m`
    (three.js: perspective, vertical fov, z up); the view's own initial camera by default."""
    eye, target = np.asarray(eye_m, dtype=np.float64), np.asarray(target_m, dtype=np.float64)
    back = (eye - target) / np.linalg.norm(eye - target)
    right = np.cross([0.0, 0.0, 1.0], back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    d = points_m - eye
    depth = -(d @ back)
    focal_px = (height / 2.0) / np.tan(CAMERA_FOV_RAD / 2.0)
    return np.column_stack([width / 2.0 + focal_px * (d @ right) / depth, height / 2.0 - focal_px * (d @ up) / depth])
