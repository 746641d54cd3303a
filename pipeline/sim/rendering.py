"""Depth rendering with pybullet's CPU (tiny) renderer, in the optical-frame convention.

Works on any pybullet client: the physics world's, or a render worker's world that only
mirrors poses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from robonav.pipeline.camera import CameraConfig, CameraIntrinsics
from robonav.pipeline.perception.depth import depth_from_opengl_buffer
from robonav.pipeline.sim.bullet import pybullet as p

# OpenGL cameras look along -z with y up; the optical frame looks along +z with y down.
_GL_FROM_OPTICAL = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class DepthFrame:
    """One rendered depth image with its labels and camera model."""

    depth_m: npt.NDArray[np.float32]
    """(H, W) depth along the optical axis [m]; +inf where nothing was hit."""
    segmentation: npt.NDArray[np.int32]
    """(H, W) pybullet body unique id per pixel; -1 for background (see `SimWorld.body_labels`)."""
    intrinsics: CameraIntrinsics
    world_from_camera: npt.NDArray[np.float64]
    """(4, 4) pose of the optical frame in the world frame."""


def render_depth(client: int, cam: CameraConfig) -> DepthFrame:
    """Render `cam` in pybullet client `client`.

    Returns:
        The depth image (linear metres along the optical axis, +inf where nothing was hit),
        per-pixel body unique ids (-1 for background), the intrinsics and the camera pose.
    """
    intrinsics = cam.intrinsics
    world_from_camera = cam.world_from_camera
    # pybullet takes OpenGL matrices flattened column-major.
    view = (_GL_FROM_OPTICAL @ np.linalg.inv(world_from_camera)).flatten(order="F")
    proj = opengl_projection_matrix(intrinsics, cam.near_m, cam.far_m).flatten(order="F")
    _, _, _, z_buffer, seg = p.getCameraImage(
        cam.width, cam.height, viewMatrix=view.tolist(), projectionMatrix=proj.tolist(),
        shadow=0, renderer=p.ER_TINY_RENDERER, physicsClientId=client)
    z_buffer = np.asarray(z_buffer, dtype=np.float32).reshape(cam.height, cam.width)
    segmentation = np.asarray(seg, dtype=np.int32).reshape(cam.height, cam.width)
    depth_m = depth_from_opengl_buffer(z_buffer, cam.near_m, cam.far_m)
    depth_m[segmentation < 0] = np.inf
    return DepthFrame(depth_m, segmentation, intrinsics, world_from_camera)


def opengl_projection_matrix(intrinsics: CameraIntrinsics, near_m: float, far_m: float) -> npt.NDArray[np.float64]:
    """(4, 4) OpenGL projection matrix that reproduces pinhole `intrinsics`.

    Pixel centers sit at integer (u, v) with v growing downwards, as in `CameraIntrinsics`;
    for centered intrinsics this equals `computeProjectionMatrixFOV(vertical fov, w/h, near, far)`.
    """
    w, h = intrinsics.width, intrinsics.height
    return np.array([
        [2.0 * intrinsics.fx / w, 0.0, 1.0 - 2.0 * (intrinsics.cx + 0.5) / w, 0.0],
        [0.0, 2.0 * intrinsics.fy / h, 2.0 * (intrinsics.cy + 0.5) / h - 1.0, 0.0],
        [0.0, 0.0, -(far_m + near_m) / (far_m - near_m), -2.0 * far_m * near_m / (far_m - near_m)],
        [0.0, 0.0, -1.0, 0.0],
    ])
