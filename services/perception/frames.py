"""A decoded camera message as the occupancy map takes it: the frame, the camera's pose, the arm's."""

from __future__ import annotations

from robonav.pipeline.camera import CameraConfig
from robonav.pipeline.perception.maps.protocol import CameraFrame
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.types import FloatArray
from robonav.pipeline.wire.messages import DepthImage, PointCloud


def camera_frame(message: PointCloud | DepthImage, camera: CameraConfig, world_from_camera: FloatArray,
                 robot: RobotModel, q: FloatArray) -> CameraFrame:
    """The frame of `message` from `camera` (posed at `world_from_camera`, (4, 4)), with the robot at
    `q` (robot joint order [rad]); a cloud without intrinsics takes the camera's."""
    if isinstance(message, DepthImage):
        depth, points, labels = message.depth_m, None, message.labels
    else:
        depth, points, labels = None, message.points, None
    return CameraFrame(intrinsics=message.intrinsics or camera.intrinsics, world_from_camera=world_from_camera,
                       world_from_link=robot.link_poses(q), depth_m=depth, points_camera_m=points, labels=labels)
