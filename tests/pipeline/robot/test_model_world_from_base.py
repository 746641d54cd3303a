"""RobotModel with `world_from_base`: every pose in the world is the base's pose times the pose at the identity."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.link_frames import LinkFrames
from robonav.pipeline.robot.model import RobotModel, resolve_urdf_path
from robonav.pipeline.transforms import PoseSpec

_AXIS = np.array([1.0, 2.0, 3.0]) / math.sqrt(14.0)
POSE = PoseSpec((0.4, -0.3, 0.25), (*(float(v) for v in _AXIS * math.sin(0.35)), math.cos(0.35)))  # 0.7 rad
"""A translation and a rotation about no coordinate axis."""
PANDA = RobotConfig(fixed_joint_positions={"panda_finger_joint1": 0.04, "panda_finger_joint2": 0.04})
"""The `panda` fixture's robot (fingers open)."""

# The base link hangs below the root on a fixed, rotated and offset joint, as the UR5's does.
MOUNTED_URDF = """<?xml version="1.0"?>
<robot name="mounted">
  <link name="mount"/>
  <link name="base"><collision><geometry><box size="0.2 0.2 0.1"/></geometry></collision></link>
  <link name="arm"><collision><origin xyz="0.15 0 0"/><geometry><box size="0.3 0.04 0.04"/></geometry></collision></link>
  <link name="tool"><collision><geometry><sphere radius="0.03"/></geometry></collision></link>
  <joint name="mount_joint" type="fixed"><parent link="mount"/><child link="base"/>
    <origin xyz="0.1 0.2 0.9" rpy="0.1 0.2 0.3"/></joint>
  <joint name="spin" type="revolute"><parent link="base"/><child link="arm"/><origin xyz="0 0 0.1"/>
    <axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="slide" type="prismatic"><parent link="arm"/><child link="tool"/><origin xyz="0.1 0 0"/>
    <axis xyz="1 0 0"/><limit lower="0.0" upper="0.2" effort="1" velocity="1"/></joint>
</robot>
"""


@pytest.fixture(scope="module")
def posed_panda() -> RobotModel:
    """The `panda` fixture's robot standing at `POSE`."""
    return RobotModel.from_config(dataclasses.replace(PANDA, world_from_base=POSE))


def _mounted(tmp_path: Path, pose: PoseSpec | None) -> RobotModel:
    urdf = tmp_path / "mounted.urdf"
    urdf.write_text(MOUNTED_URDF, encoding="utf-8")
    cfg = RobotConfig(name="mounted", urdf=str(urdf), base_link="base", end_effector_link="tool",
                      joint_names=("spin", "slide"), max_velocity_rad_s=(1.0, 1.0), max_acceleration_rad_s2=(1.0, 1.0),
                      max_jerk_rad_s3=(10.0, 10.0), home_position_rad=(0.0, 0.0))
    return RobotModel.from_config(cfg if pose is None else dataclasses.replace(cfg, world_from_base=pose))


def test_every_pose_is_world_from_base_times_the_pose_at_identity(panda: RobotModel, posed_panda: RobotModel) -> None:
    world_from_base = POSE.matrix
    qs = np.random.default_rng(11).uniform(panda.lower_limits_rad, panda.upper_limits_rad, size=(20, panda.dof))
    for q in qs:
        np.testing.assert_allclose(posed_panda.link_pose_stack(q), world_from_base @ panda.link_pose_stack(q),
                                   atol=1e-12, rtol=0)
        # Links, the end effector, a joint frame and a link without geometry.
        for frame in ("panda_link0", "panda_hand", "panda_joint4", "panda_link8"):
            np.testing.assert_allclose(posed_panda.frame_pose(q, frame), world_from_base @ panda.frame_pose(q, frame),
                                       atol=1e-12, rtol=0, err_msg=frame)
        poses = posed_panda.link_poses(q)
        np.testing.assert_allclose(poses["panda_link0"], world_from_base, atol=1e-12, rtol=0)
    batch, reference = posed_panda.link_poses_batch(qs), panda.link_poses_batch(qs)
    for name, stack in batch.items():
        np.testing.assert_allclose(stack, world_from_base @ reference[name], atol=1e-12, rtol=0, err_msg=name)
    # What is in the robot's own frames does not move with it.
    assert posed_panda.static_link_names == panda.static_link_names
    for name, hull in posed_panda.link_hull_vertices.items():
        np.testing.assert_array_equal(hull, panda.link_hull_vertices[name])


def test_a_base_below_the_root_stands_at_world_from_base(tmp_path: Path) -> None:
    at_identity, posed = _mounted(tmp_path, None), _mounted(tmp_path, POSE)
    rng = np.random.default_rng(5)
    for q in rng.uniform(at_identity.lower_limits_rad, at_identity.upper_limits_rad, size=(10, 2)):
        np.testing.assert_allclose(at_identity.frame_pose(q, "base"), np.eye(4), atol=1e-12, rtol=0)
        np.testing.assert_allclose(posed.frame_pose(q, "base"), POSE.matrix, atol=1e-12, rtol=0)
        for frame in ("mount", "arm", "tool"):
            np.testing.assert_allclose(posed.frame_pose(q, frame), POSE.matrix @ at_identity.frame_pose(q, frame),
                                       atol=1e-12, rtol=0, err_msg=frame)
        np.testing.assert_allclose(posed.link_pose_stack(q), POSE.matrix @ at_identity.link_pose_stack(q),
                                   atol=1e-12, rtol=0)
    # The root hangs 0.9 m below the base (the fixed joint's offset, rotated).
    assert at_identity.frame_pose(np.zeros(2), "mount")[2, 3] < -0.8


def test_a_pose_for_a_base_that_moves_is_refused() -> None:
    with pytest.raises(ValueError, match=r"world_from_base must be the identity when robot.base_link 'panda_link3' "
                                         r"moves with a joint"):
        RobotModel.from_config(RobotConfig(base_link="panda_link3", world_from_base=POSE))
    # At the identity a moving base stays what it was: the world follows that link.
    robot = RobotModel.from_config(RobotConfig(base_link="panda_link3"))
    np.testing.assert_allclose(robot.frame_pose(robot.home_position_rad, "panda_link3"), np.eye(4), atol=1e-12)


def test_link_frames_place_every_link_as_the_model_does(posed_panda: RobotModel) -> None:
    urdf = resolve_urdf_path(posed_panda.config.urdf).read_text(encoding="utf-8")
    frames = LinkFrames(urdf, "panda_link0", PANDA.fixed_joint_positions, world_from_base=POSE.matrix)
    q = np.random.default_rng(2).uniform(posed_panda.lower_limits_rad, posed_panda.upper_limits_rad)
    poses = frames.world_from_links(dict(zip(posed_panda.joint_names, q.tolist(), strict=True)))
    for name in ("panda_link0", "panda_link4", "panda_hand", "panda_leftfinger"):
        np.testing.assert_allclose(poses[name], posed_panda.frame_pose(q, name), atol=1e-12, rtol=0, err_msg=name)
    with pytest.raises(ValueError, match="world_from_base must be a finite"):
        LinkFrames(urdf, "panda_link0", world_from_base=np.full((4, 4), np.nan))


def test_pose_spec_refuses_non_finite_and_non_unit_values() -> None:
    with pytest.raises(ValueError, match="must be finite"):
        PoseSpec((0.0, math.inf, 0.0), (0.0, 0.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="must be finite"):
        PoseSpec((0.0, 0.0, 0.0), (0.0, 0.0, math.nan, 1.0))
    with pytest.raises(ValueError, match="unit quaternion"):
        PoseSpec((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.5))
