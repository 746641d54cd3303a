"""Compiled forward kinematics equals Pinocchio's for the Panda, the KUKA iiwa and odd joint types."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.lane_kinematics import LinkKinematics
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.transforms import PoseSpec

KUKA = RobotConfig(
    name="iiwa", urdf="pybullet_data:kuka_iiwa/model.urdf", base_link="lbr_iiwa_link_0",
    end_effector_link="lbr_iiwa_link_7", joint_names=tuple(f"lbr_iiwa_joint_{i}" for i in range(1, 8)),
    max_velocity_rad_s=(1.0,) * 7, max_acceleration_rad_s2=(1.0,) * 7, max_jerk_rad_s3=(1.0,) * 7,
    home_position_rad=(0.0,) * 7,
)

# Two links, an arbitrary-axis revolute joint, a prismatic joint along y and a rotated placement.
ODD_URDF = """<robot name="odd">
  <link name="base"><collision><geometry><box size="0.1 0.1 0.1"/></geometry></collision></link>
  <link name="arm"><collision><origin xyz="0 0 0.1"/><geometry><cylinder radius="0.03" length="0.2"/></geometry></collision></link>
  <link name="slider"><collision><geometry><box size="0.05 0.05 0.05"/></geometry></collision></link>
  <joint name="j1" type="revolute"><parent link="base"/><child link="arm"/><origin xyz="0 0 0.1" rpy="0.3 0 0.2"/>
    <axis xyz="0.3 0.5 0.8"/><limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <joint name="j2" type="prismatic"><parent link="arm"/><child link="slider"/><origin xyz="0 0.05 0.2" rpy="0 0.4 0"/>
    <axis xyz="0 1 0"/><limit lower="-0.1" upper="0.2" effort="1" velocity="1"/></joint>
</robot>"""


def _assert_matches(robot: RobotModel, seed: int, count: int = 200) -> None:
    kinematics = LinkKinematics.from_robot(robot)
    rng = np.random.default_rng(seed)
    qs = rng.uniform(robot.lower_limits_rad, robot.upper_limits_rad, size=(count, robot.dof))
    compiled = kinematics.link_poses_batch(qs)
    for i in range(count):
        np.testing.assert_allclose(compiled[i], robot.link_pose_stack(qs[i]), atol=1e-9, rtol=0)
    np.testing.assert_allclose(kinematics.link_pose_stack(qs[0]), compiled[0], atol=0, rtol=0)
    # The lane kinematics (several states per call, joint frames) give the same link poses.
    joint_from_link = np.tile(np.eye(4), (kinematics.link_count, 1, 1))
    joint_from_link[:, :3, :3] = kinematics.joint_from_link_rotation
    joint_from_link[:, :3, 3] = kinematics.joint_from_link_translation_m
    lanes = kinematics.joint_poses_lanes(qs)
    np.testing.assert_allclose(lanes[:, kinematics.link_joint] @ joint_from_link, compiled, atol=1e-9, rtol=0)


def test_panda_matches_pinocchio(panda: RobotModel) -> None:
    _assert_matches(panda, seed=1)


def test_kuka_iiwa_matches_pinocchio() -> None:
    _assert_matches(RobotModel.from_config(KUKA), seed=2)


def test_robot_standing_elsewhere_matches_pinocchio(panda: RobotModel) -> None:
    # Rotated about a tilted axis and moved: the lane tables come out in the world as the model's.
    posed = RobotModel.from_config(dataclasses.replace(
        panda.config, world_from_base=PoseSpec((-0.5, 0.7, 0.3), (0.2, -0.3, 0.4, 0.8426149773176358))))
    _assert_matches(posed, seed=6, count=50)
    q = posed.home_position_rad
    np.testing.assert_allclose(LinkKinematics.from_robot(posed).link_pose_stack(q),
                               posed.config.world_from_base.matrix @ panda.link_pose_stack(q), atol=1e-9, rtol=0)


def test_base_below_a_planning_joint_matches_pinocchio() -> None:
    # The world frame is panda_link3: world_from_root changes with q1..q3.
    _assert_matches(RobotModel.from_config(RobotConfig(base_link="panda_link3")), seed=3, count=50)


def test_unaligned_revolute_and_prismatic_joints(tmp_path: Path) -> None:
    urdf = tmp_path / "odd.urdf"
    urdf.write_text(ODD_URDF)
    robot = RobotModel.from_config(RobotConfig(
        name="odd", urdf=str(urdf), base_link="base", end_effector_link="slider", joint_names=("j1", "j2"),
        max_velocity_rad_s=(1.0, 1.0), max_acceleration_rad_s2=(1.0, 1.0), max_jerk_rad_s3=(1.0, 1.0),
        home_position_rad=(0.0, 0.0)))
    _assert_matches(robot, seed=4, count=50)


def test_rejects_wrong_shape(panda: RobotModel) -> None:
    with pytest.raises(ValueError, match="shape"):
        LinkKinematics.from_robot(panda).link_poses_batch(np.zeros((2, 3)))
