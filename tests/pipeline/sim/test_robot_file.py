"""The sim loads a robot file's URDF as the planner does: package:// meshes, its root link as the world frame."""

from __future__ import annotations

import numpy as np

from robonav.pipeline.camera import CameraConfig
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.sim.config import SimConfig
from robonav.pipeline.sim.world import SimWorld
from robonav.services.config import load_robot_file

from ...conftest import REPO_ROOT

CAMERA = CameraConfig(width=64, height=48)


def test_the_ur5_stands_where_the_planner_puts_it() -> None:
    cfg = load_robot_file(REPO_ROOT / "configs" / "ur5.yaml")
    robot = RobotModel.from_config(cfg)
    q = np.array([0.3, -1.2, 1.0, -1.4, -1.2, 0.5])
    wrist_m = robot.frame_pose(q, "wrist_2_link")[:3, 3]
    assert wrist_m[2] > 0.9144  # the arm stands on offset_link's 0.9144 m pedestal
    with SimWorld(cfg, CAMERA, SimConfig(follow="kinematic")) as world:
        world.set_joint_positions(q)
        np.testing.assert_allclose(world.joint_state()[0], q, atol=1e-9)
        world.add_object(SceneObject("probe", "sphere", tuple(wrist_m), radius_m=0.02))
        world.step()
        assert {c.object for c in world.robot_obstacle_contacts()} == {"probe"}
        world.set_object_pose("probe", wrist_m + np.array([0.0, 0.0, 0.5]))
        world.step()
        assert world.robot_obstacle_contacts() == []


def test_loading_a_urdf_without_inertials_prints_nothing(capfd) -> None:  # noqa: ANN001
    # The UR5's URDF has links without <inertial>: pybullet's importer warns on stdout for each.
    cfg = load_robot_file(REPO_ROOT / "configs" / "ur5.yaml")
    capfd.readouterr()
    with SimWorld(cfg, CAMERA, SimConfig(follow="kinematic")):
        pass
    out, err = capfd.readouterr()
    assert out == "" and err == "", (out[:300], err[:300])
