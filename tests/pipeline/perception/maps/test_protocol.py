"""Both occupancy backends behind one protocol: same frame in, the same obstacle out; refused frames named."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from robonav.pipeline.camera import CameraConfig
from robonav.pipeline.perception.config import PerceptionConfig
from robonav.pipeline.perception.depth import points_from_depth
from robonav.pipeline.perception.maps.factory import make_occupancy_map
from robonav.pipeline.perception.maps.octree import OccupancyMap
from robonav.pipeline.perception.maps.projection import ProjectionOccupancyMap
from robonav.pipeline.perception.maps.protocol import CameraFrame, FrameRejected
from robonav.pipeline.perception.self_filter import SelfFilter
from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.sim.config import SimConfig
from robonav.pipeline.sim.world import SimWorld
from robonav.pipeline.transforms import look_at_quat_xyzw

ROBOT = RobotConfig()
HOME = np.array(ROBOT.home_position_rad)
RES = 0.02
BOX = SceneObject("box", "box", (0.55, 0.25, 0.3), size_m=(0.16, 0.16, 0.2))
EYE = (1.45, 0.55, 1.05)
CAMERA = CameraConfig(width=320, height=240, position_m=EYE, quat_xyzw=tuple(look_at_quat_xyzw(EYE, (0.55, 0.0, 0.25))))


@pytest.fixture(scope="module")
def scene() -> tuple[RobotModel, SelfFilter, CameraFrame]:
    robot = RobotModel.from_config(ROBOT)
    with SimWorld(ROBOT, CAMERA, SimConfig(objects=(BOX,), follow="kinematic", gravity=False)) as world:
        world.set_joint_target(HOME)
        world.step()
        rendered = world.render_depth()
    frame = CameraFrame(rendered.intrinsics, rendered.world_from_camera, robot.link_poses(HOME),
                        points_camera_m=points_from_depth(rendered.depth_m, rendered.intrinsics))
    return robot, SelfFilter(robot.link_hull_vertices, 0.04), frame


@pytest.mark.parametrize("clearing", ["projection", "raycast"])
def test_each_backend_maps_the_box_through_integrate(scene, clearing: str) -> None:
    _, self_filter, frame = scene
    config = PerceptionConfig(resolution_m=RES, fill_below_surfaces=False, clearing=clearing)
    occupancy = make_occupancy_map(config)
    assert isinstance(occupancy, ProjectionOccupancyMap if clearing == "projection" else OccupancyMap)
    stages = occupancy.integrate(frame, self_filter=self_filter, clear_filter=self_filter)
    assert stages and all(ms >= 0.0 for ms in stages.values())
    centers = occupancy.occupied_centers_m()
    lo = np.asarray(BOX.position_m) - np.asarray(BOX.size_m) / 2 - RES
    hi = np.asarray(BOX.position_m) + np.asarray(BOX.size_m) / 2 + RES
    on_box = np.all((centers >= lo) & (centers <= hi), axis=1)
    assert on_box.sum() > 30 and on_box.mean() > 0.9  # the camera sees the box (the floor is outside the crop)
    voxels = occupancy.occupied_voxels()
    np.testing.assert_allclose(voxels.centers_m, centers)
    np.testing.assert_allclose((voxels.ijk - voxels.ijk.min(axis=0)) * RES,
                               centers - centers.min(axis=0), atol=1e-9)  # one grid, whatever its origin
    assert occupancy.voxel_count == centers.shape[0]
    freed = occupancy.free_where(lambda c: c[:, 1] > BOX.position_m[1])
    assert freed > 0 and occupancy.voxel_count == centers.shape[0] - freed
    occupancy.clear()
    assert occupancy.voxel_count == 0


def test_a_frame_a_backend_cannot_use_is_rejected_with_its_reason(scene) -> None:
    _, self_filter, frame = scene
    blind = dataclasses.replace(frame, points_camera_m=np.full((10, 3), np.nan))
    with pytest.raises(FrameRejected) as empty:
        make_occupancy_map(PerceptionConfig()).integrate(blind, self_filter=self_filter, clear_filter=self_filter)
    assert empty.value.reason == "empty"
    depth = CameraFrame(frame.intrinsics, frame.world_from_camera, frame.world_from_link,
                        depth_m=np.ones((frame.intrinsics.height, frame.intrinsics.width)))
    with pytest.raises(FrameRejected) as unsupported:
        make_occupancy_map(PerceptionConfig(clearing="raycast")).integrate(depth, self_filter=self_filter,
                                                                           clear_filter=self_filter)
    assert unsupported.value.reason == "unsupported"


def test_a_frame_holds_exactly_one_kind_of_data(scene) -> None:
    _, _, frame = scene
    with pytest.raises(ValueError, match="exactly one"):
        dataclasses.replace(frame, depth_m=np.ones((2, 2)))
    with pytest.raises(ValueError, match="exactly one"):
        CameraFrame(frame.intrinsics, frame.world_from_camera, frame.world_from_link)
