"""Link poses from the URDF text alone (what a recording or a remote viewer has): they agree
with the planner's model, and continuous, prismatic, mimic and held joints move their links."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robonav.pipeline.robot.link_frames import LinkFrames
from robonav.pipeline.robot.model import RobotModel, resolve_urdf_path

# A base, a continuous joint about z, a prismatic slide along x and a mimic joint that follows
# the slide at twice its travel, 0.1 m further out.
TOY_URDF = """<robot name="toy">
  <link name="base"/><link name="turret"/><link name="slider"/><link name="twin"/>
  <joint name="spin" type="continuous"><parent link="base"/><child link="turret"/>
    <origin xyz="0 0 0.5"/><axis xyz="0 0 1"/></joint>
  <joint name="slide" type="prismatic"><parent link="turret"/><child link="slider"/>
    <axis xyz="1 0 0"/><limit lower="0" upper="1" effort="1" velocity="1"/></joint>
  <joint name="follow" type="prismatic"><parent link="turret"/><child link="twin"/>
    <axis xyz="1 0 0"/><limit lower="0" upper="2" effort="1" velocity="1"/>
    <mimic joint="slide" multiplier="2" offset="0.1"/></joint>
</robot>"""


def test_panda_links_agree_with_the_planner_model(panda: RobotModel) -> None:
    frames = LinkFrames(resolve_urdf_path(panda.config.urdf).read_text(encoding="utf-8"), panda.config.base_link,
                        panda.config.fixed_joint_positions)
    rng = np.random.default_rng(4)
    for _ in range(5):
        q = rng.uniform(panda.lower_limits_rad, panda.upper_limits_rad)
        poses = frames.world_from_links(dict(zip(panda.joint_names, q.tolist(), strict=True)))
        assert set(poses) >= set(panda.link_poses(q)) | {"panda_link8", "panda_grasptarget"}
        for link, pose in panda.link_poses(q).items():
            np.testing.assert_allclose(poses[link], pose, atol=1e-12)
        np.testing.assert_allclose(poses["panda_link0"], np.eye(4), atol=1e-12)


def test_continuous_prismatic_and_mimic_joints_place_their_links() -> None:
    frames = LinkFrames(TOY_URDF, "base")
    assert set(frames.joint_names) == {"spin", "slide", "follow"}
    poses = frames.world_from_links({"spin": math.pi / 2, "slide": 0.3})
    # Turned a quarter about z, x points along world y.
    np.testing.assert_allclose(poses["slider"][:3, 3], [0.0, 0.3, 0.5], atol=1e-12)
    np.testing.assert_allclose(poses["twin"][:3, 3], [0.0, 0.7, 0.5], atol=1e-12)  # 2 * 0.3 + 0.1
    # A state that names the mimic joint sets it; one that names nothing leaves joints at 0.
    np.testing.assert_allclose(frames.world_from_links({"follow": 0.2})["twin"][:3, 3], [0.2, 0.0, 0.5], atol=1e-12)
    held = LinkFrames(TOY_URDF, "base", {"slide": 0.5})
    np.testing.assert_allclose(held.world_from_links({})["slider"][:3, 3], [0.5, 0.0, 0.5], atol=1e-12)


def test_a_base_below_the_root_is_the_world() -> None:
    poses = LinkFrames(TOY_URDF, "turret").world_from_links({"spin": 1.0, "slide": 0.25})
    np.testing.assert_allclose(poses["turret"], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(poses["base"][:3, 3], [0.0, 0.0, -0.5], atol=1e-12)
    np.testing.assert_allclose(poses["slider"][:3, 3], [0.25, 0.0, 0.0], atol=1e-12)


def test_path_positions_follow_each_row() -> None:
    frames = LinkFrames(TOY_URDF, "base")
    points = frames.link_positions(("spin", "slide"), np.array([[0.0, 0.1], [math.pi, 0.2]]), "slider")
    np.testing.assert_allclose(points, [[0.1, 0.0, 0.5], [-0.2, 0.0, 0.5]], atol=1e-12)


@pytest.mark.parametrize(("urdf", "base", "message"), [
    ("<robot", "base", "cannot be read"),
    (TOY_URDF, "nowhere", "not a link"),
])
def test_bad_descriptions_fail_clearly(urdf: str, base: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        LinkFrames(urdf, base)


def test_bad_positions_and_paths_fail_clearly() -> None:
    frames = LinkFrames(TOY_URDF, "base")
    with pytest.raises(ValueError, match="finite"):
        frames.world_from_links({"slide": float("nan")})
    with pytest.raises(ValueError, match="shape"):
        frames.link_positions(("spin", "slide"), np.zeros((3, 3)), "slider")
    with pytest.raises(ValueError, match="not a link"):
        frames.link_positions(("spin",), np.zeros((3, 1)), "gripper")


def test_tree_transforms_compose_to_the_link_poses() -> None:
    frames = LinkFrames(TOY_URDF, "turret")
    positions = {"spin": 0.7, "slide": 0.4}
    tree = frames.tree_transforms(positions)
    assert [(parent, child) for parent, child, _ in tree] == [
        ("world", "base"), ("base", "turret"), ("turret", "slider"), ("turret", "twin")]
    parent_of = {child: (parent, pose) for parent, child, pose in tree}
    for link, expected in frames.world_from_links(positions).items():
        pose, frame = np.eye(4), link
        while frame != "world":  # walk up to the world, as a viewer's transform tree does
            parent, parent_from_child = parent_of[frame]
            pose, frame = parent_from_child @ pose, parent
        np.testing.assert_allclose(pose, expected, atol=1e-12)
