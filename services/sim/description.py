"""The sim's `cameras` publication: every camera of the cell, as the camera owner knows it."""

from __future__ import annotations

import time

from robonav.pipeline.wire.messages import CameraDescription, Cameras
from robonav.services.config import RobonavConfig, perceived_world_from_camera


def camera_descriptions(cfg: RobonavConfig, stamp: float | None = None) -> Cameras:
    """Every configured camera with its intrinsics and the pose perception uses (the calibrated one
    when the camera names an extrinsics file), so clients place clouds and images as perception does."""
    return Cameras(stamp=time.time() if stamp is None else stamp, cameras=tuple(
        CameraDescription(camera_id=c.camera_id, intrinsics=c.intrinsics, world_from_camera=perceived_world_from_camera(c),
                          output=c.output, near_m=c.near_m, far_m=c.far_m, rate_hz=c.rate_hz) for c in cfg.cameras))
