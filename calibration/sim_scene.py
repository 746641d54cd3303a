"""A pybullet (DIRECT) scene for hand-eye calibration: the robot and a ChArUco board, rendered in RGB.

The board is a textured quad (a ChArUco texture renders cleanly on a quad; on a box's faces
pybullet maps it unpredictably), either carried by the end effector or fixed in the world.
Images come from pybullet's CPU TinyRenderer with flat lighting, rendered `supersample`
times larger and averaged down, as a sensor integrates light over each pixel, plus optional
Gaussian sensor noise.

Measured here: TinyRenderer's principal point is half a pixel right of and half a pixel
above the one its projection matrix states, i.e. (W/2, H/2 - 1) for the centered matrix of
`computeProjectionMatrixFOV` (a board rendered at a known pose shows a constant
(+0.5, -0.5) px offset against OpenCV's projection). `render_rgb` cancels it, so the images
follow the requested intrinsics exactly.
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from robonav.calibration.board import BoardSpec, board_image
from robonav.calibration.dataset import IntrinsicsSpec
from robonav.pipeline.camera import CameraConfig
from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.model import resolve_urdf_path
from robonav.pipeline.sim.bullet import pybullet as p
from robonav.pipeline.transforms import quat_xyzw_from_rotation
from robonav.pipeline.types import FloatArray

TINY_RENDERER_PIXEL_OFFSET = (0.5, -0.5)
"""Effective minus stated principal point of TinyRenderer renders [px of the render]."""
BOARD_MARGIN_SQUARES = 0.5
"""White border around the printed squares, so markers on the edge stand out against anything."""
PIXELS_PER_SQUARE = 128
_GL_FROM_OPTICAL = np.diag([1.0, -1.0, -1.0, 1.0])
_NEAR_M, _FAR_M = 0.03, 6.0


def camera_intrinsics(camera: CameraConfig, width: int, height: int) -> IntrinsicsSpec:
    """Square-pixel, centered intrinsics of `camera`'s vertical field of view at width x height."""
    fy = 0.5 * height / math.tan(math.radians(camera.vertical_fov_deg) / 2.0)
    return IntrinsicsSpec(width, height, fy, fy, (width - 1) / 2.0, (height - 1) / 2.0)


def projection_matrix(intrinsics: IntrinsicsSpec, supersample: int) -> FloatArray:
    """(4, 4) OpenGL projection whose TinyRenderer render, averaged over supersample² blocks, has `intrinsics`."""
    s = supersample
    w, h = intrinsics.width * s, intrinsics.height * s
    # Pixel i of the averaged image is the mean of render pixels s*i .. s*i+s-1, centered at s*i + (s-1)/2.
    cx = s * intrinsics.cx + (s - 1) / 2.0 - TINY_RENDERER_PIXEL_OFFSET[0]
    cy = s * intrinsics.cy + (s - 1) / 2.0 - TINY_RENDERER_PIXEL_OFFSET[1]
    fx, fy = s * intrinsics.fx, s * intrinsics.fy
    return np.array([
        [2.0 * fx / w, 0.0, 1.0 - 2.0 * (cx + 0.5) / w, 0.0],
        [0.0, 2.0 * fy / h, 2.0 * (cy + 0.5) / h - 1.0, 0.0],
        [0.0, 0.0, -(_FAR_M + _NEAR_M) / (_FAR_M - _NEAR_M), -2.0 * _FAR_M * _NEAR_M / (_FAR_M - _NEAR_M)],
        [0.0, 0.0, -1.0, 0.0],
    ])


class CalibrationScene:
    """The robot (fixed base at `robot.world_from_base`) and a board quad; pose both, then render."""

    def __init__(self, robot: RobotConfig, board: BoardSpec) -> None:
        self._client = p.connect(p.DIRECT)
        try:
            quat = np.asarray(robot.world_from_base.quat_xyzw, dtype=np.float64)
            self._robot = p.loadURDF(str(resolve_urdf_path(robot.urdf, robot.package_paths)), useFixedBase=True,
                                     basePosition=list(robot.world_from_base.position_m),
                                     baseOrientation=(quat / np.linalg.norm(quat)).tolist(),
                                     flags=p.URDF_USE_MATERIAL_COLORS_FROM_MTL, physicsClientId=self._client)
            names = {p.getJointInfo(self._robot, j, physicsClientId=self._client)[1].decode(): j
                     for j in range(p.getNumJoints(self._robot, physicsClientId=self._client))}
            self._joints = [names[n] for n in robot.joint_names]
            for name, value in robot.fixed_joint_positions.items():
                p.resetJointState(self._robot, names[name], value, physicsClientId=self._client)
            self._board = self._create_board(board)
        except Exception:
            p.disconnect(self._client)
            raise

    def _create_board(self, board: BoardSpec) -> int:
        width, height = board.size_m
        margin = BOARD_MARGIN_SQUARES * board.square_length_m
        x0, y0, x1, y1 = -margin, -margin, width + margin, height + margin
        vertices = [[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]]
        # Texture row 0 (top of the print) is at v = 1, board y = y0.
        uvs = [[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]]
        # Both windings, so the quad renders from either side.
        indices = [0, 2, 1, 0, 3, 2, 0, 1, 2, 0, 2, 3]
        visual = p.createVisualShape(p.GEOM_MESH, vertices=vertices, indices=indices, uvs=uvs,
                                     normals=[[0.0, 0.0, -1.0]] * 4, physicsClientId=self._client)
        body = p.createMultiBody(baseMass=0.0, baseVisualShapeIndex=visual, physicsClientId=self._client)
        image = board_image(board, pixels_per_square=PIXELS_PER_SQUARE, margin_squares=BOARD_MARGIN_SQUARES)
        with tempfile.TemporaryDirectory(prefix="robonav-board-") as tmp:
            path = Path(tmp) / "charuco.png"
            cv2.imwrite(str(path), image)
            texture = p.loadTexture(str(path), physicsClientId=self._client)
        p.changeVisualShape(body, -1, textureUniqueId=texture, rgbaColor=[1, 1, 1, 1], physicsClientId=self._client)
        return body

    def set_joint_positions(self, q: npt.ArrayLike) -> None:
        for joint, value in zip(self._joints, np.asarray(q, dtype=np.float64)):
            p.resetJointState(self._robot, joint, float(value), physicsClientId=self._client)

    def set_board_pose(self, world_from_board: FloatArray) -> None:
        p.resetBasePositionAndOrientation(self._board, world_from_board[:3, 3].tolist(),
                                          quat_xyzw_from_rotation(world_from_board[:3, :3]).tolist(),
                                          physicsClientId=self._client)

    def render_rgb(self, world_from_camera: FloatArray, intrinsics: IntrinsicsSpec, *, supersample: int = 3,
                   noise_std: float = 0.0, rng: np.random.Generator | None = None) -> npt.NDArray[np.uint8]:
        """(H, W, 3) RGB image of the scene from an optical-frame camera pose."""
        s = supersample
        view = (_GL_FROM_OPTICAL @ np.linalg.inv(world_from_camera)).flatten(order="F")
        projection = projection_matrix(intrinsics, s).flatten(order="F")
        w, h = intrinsics.width * s, intrinsics.height * s
        _, _, rgba, _, _ = p.getCameraImage(w, h, viewMatrix=view.tolist(), projectionMatrix=projection.tolist(),
                                            renderer=p.ER_TINY_RENDERER, shadow=0, lightAmbientCoeff=1.0,
                                            lightDiffuseCoeff=0.0, lightSpecularCoeff=0.0,
                                            physicsClientId=self._client)
        image = np.asarray(rgba, dtype=np.uint8).reshape(h, w, 4)[:, :, :3].astype(np.float32)
        image = image.reshape(intrinsics.height, s, intrinsics.width, s, 3).mean(axis=(1, 3))
        if noise_std > 0:
            if rng is None:
                raise ValueError("noise_std > 0 needs an rng")
            image += rng.normal(0.0, noise_std, image.shape)
        return np.clip(np.rint(image), 0, 255).astype(np.uint8)

    def close(self) -> None:
        if p.isConnected(self._client):
            p.disconnect(self._client)

    def __enter__(self) -> CalibrationScene:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
