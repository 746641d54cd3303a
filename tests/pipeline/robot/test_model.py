"""RobotModel on pybullet_data's Panda: FK, limits, link geometry, input validation."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pybullet
import pytest

from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.link_geometry import load_mesh
from robonav.pipeline.robot.model import RobotModel, resolve_urdf_path

PANDA_LINKS = (
    "panda_link0", "panda_link1", "panda_link2", "panda_link3", "panda_link4", "panda_link5",
    "panda_link6", "panda_link7", "panda_hand", "panda_leftfinger", "panda_rightfinger",
)


def _inside_hull(hull_vertices: np.ndarray, hull_triangles: np.ndarray, points: np.ndarray, tol: float = 1e-7) -> bool:
    a, b, c = (hull_vertices[hull_triangles[:, k]] for k in range(3))
    normals = np.cross(b - a, c - a)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    signed = np.einsum("pfj,fj->pf", points[:, None, :] - a[None], normals)
    return bool(np.all(signed <= tol))


def test_joint_names_limits_and_config_limits(panda: RobotModel) -> None:
    assert panda.joint_names == tuple(f"panda_joint{i}" for i in range(1, 8))
    assert panda.dof == 7
    # pybullet_data's panda.urdf <limit> values (joint4's upper limit is 0.0 in this file).
    np.testing.assert_allclose(panda.lower_limits_rad, [-2.9671, -1.8326, -2.9671, -3.1416, -2.9671, -0.0873, -2.9671])
    np.testing.assert_allclose(panda.upper_limits_rad, [2.9671, 1.8326, 2.9671, 0.0, 2.9671, 3.8223, 2.9671])
    np.testing.assert_allclose(panda.velocity_limits, panda.config.max_velocity_rad_s)
    np.testing.assert_allclose(panda.acceleration_limits, panda.config.max_acceleration_rad_s2)
    np.testing.assert_allclose(panda.jerk_limits, panda.config.max_jerk_rad_s3)


def test_home_fk_is_sane(panda: RobotModel) -> None:
    poses = panda.link_poses(panda.home_position_rad)
    assert tuple(poses) == PANDA_LINKS
    np.testing.assert_allclose(poses["panda_link0"], np.eye(4), atol=1e-12)
    for name, pose in poses.items():
        rotation = pose[:3, :3]
        np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-9, err_msg=name)
        assert np.linalg.det(rotation) == pytest.approx(1.0), name
        np.testing.assert_array_equal(pose[3], [0, 0, 0, 1])
    hand = poses["panda_hand"]
    assert hand[2, 3] > 0.4  # hand well above the base
    assert hand[2, 2] < -0.99  # hand z axis (approach direction) points down at home
    np.testing.assert_allclose(poses["panda_link1"][:3, 3], [0, 0, 0.333], atol=1e-12)
    # The grasp target is 0.105 m along the hand's z axis.
    target = panda.frame_pose(panda.home_position_rad, "panda_grasptarget")
    np.testing.assert_allclose(target[:3, 3], hand[:3, 3] + 0.105 * hand[:3, 2], atol=1e-9)
    # Fingers held at the configured 0.04 m, along the hand's y axis, in opposite directions.
    left = poses["panda_leftfinger"][:3, 3] - hand[:3, 3]
    right = poses["panda_rightfinger"][:3, 3] - hand[:3, 3]
    assert left @ hand[:3, 1] == pytest.approx(0.04) and right @ hand[:3, 1] == pytest.approx(-0.04)


def test_fk_matches_pybullet(panda: RobotModel) -> None:
    client = pybullet.connect(pybullet.DIRECT)
    try:
        body = pybullet.loadURDF(str(resolve_urdf_path(panda.config.urdf)), useFixedBase=True, physicsClientId=client)
        names = {pybullet.getJointInfo(body, j, physicsClientId=client)[12].decode(): j
                 for j in range(pybullet.getNumJoints(body, physicsClientId=client))}
        rng = np.random.default_rng(7)
        for q in rng.uniform(panda.lower_limits_rad, panda.upper_limits_rad, size=(5, 7)):
            for joint, value in zip(panda.joint_names, q):
                pybullet.resetJointState(body, names[joint.replace("joint", "link")], value, physicsClientId=client)
            for finger in ("panda_leftfinger", "panda_rightfinger"):
                pybullet.resetJointState(body, names[finger], 0.04, physicsClientId=client)
            ours = panda.link_poses(q)
            for link in ("panda_link3", "panda_link7", "panda_hand", "panda_leftfinger"):
                state = pybullet.getLinkState(body, names[link], computeForwardKinematics=True, physicsClientId=client)
                np.testing.assert_allclose(ours[link][:3, 3], state[4], atol=1e-6, err_msg=link)
    finally:
        pybullet.disconnect(client)


def test_link_poses_batch_matches_single(panda: RobotModel) -> None:
    qs = np.random.default_rng(1).uniform(panda.lower_limits_rad, panda.upper_limits_rad, size=(4, 7))
    batch = panda.link_poses_batch(qs)
    for k, q in enumerate(qs):
        for name, pose in panda.link_poses(q).items():
            np.testing.assert_allclose(batch[name][k], pose)
    with pytest.raises(ValueError, match=r"qs must have shape \(M, 7\)"):
        panda.link_poses_batch(np.zeros(7))


def test_validate_q_and_limit_check(panda: RobotModel) -> None:
    with pytest.raises(ValueError, match=r"q must have shape \(7,\)"):
        panda.validate_q(np.zeros(6))
    q = panda.home_position_rad.copy()
    q[3] = np.nan
    with pytest.raises(ValueError, match=r"q_start\[3\] \(panda_joint4\) must be finite"):
        panda.validate_q(q, "q_start")
    with pytest.raises(ValueError, match=r"q\[3\]"):
        panda.link_poses(q)
    assert panda.check_joint_limits(panda.home_position_rad) == []
    q = panda.home_position_rad.copy()
    q[3] = 0.1
    (violation,) = panda.check_joint_limits(q)
    assert "panda_joint4" in violation and "0.1000" in violation and "0.0000" in violation


def test_collision_shapes_and_hulls(panda: RobotModel) -> None:
    shapes = panda.link_collision_shapes
    assert tuple(shapes) == PANDA_LINKS
    for link, link_shapes in shapes.items():
        (shape,) = link_shapes
        assert shape.kind == "mesh" and shape.triangles is not None and shape.vertices is not None
        assert shape.triangles.shape[1] == 3 and shape.triangles.max() < len(shape.vertices)
        mesh_in_link = shape.vertices @ shape.link_from_shape[:3, :3].T + shape.link_from_shape[:3, 3]
        assert _inside_hull(shape.hull_vertices, shape.hull_triangles, mesh_in_link), link
        # One shape per link: the link hull is that shape's hull.
        link_hull = {tuple(v) for v in panda.link_hull_vertices[link].round(9)}
        assert link_hull == {tuple(v) for v in shape.hull_vertices.round(9)}
    # link6.obj carries `l` line records; its faces still load.
    assert shapes["panda_link6"][0].triangles.shape[0] == 1308
    # The right finger's collision <origin> turns it by pi about z.
    np.testing.assert_allclose(shapes["panda_rightfinger"][0].link_from_shape[:2, :2], -np.eye(2), atol=1e-9)


def test_adjacency_skips_geometry_less_links(panda: RobotModel) -> None:
    pairs = panda.adjacent_link_pairs
    assert ("panda_hand", "panda_link7") in pairs  # through panda_link8, which has no geometry
    assert ("panda_link0", "panda_link1") in pairs
    assert ("panda_leftfinger", "panda_rightfinger") not in pairs
    assert len(pairs) == 10


def test_static_links_are_the_ones_no_joint_moves(panda: RobotModel) -> None:
    assert panda.static_link_names == ("panda_link0",)
    rng = np.random.default_rng(4)
    poses = panda.link_poses_batch(rng.uniform(panda.lower_limits_rad, panda.upper_limits_rad, (5, panda.dof)))
    for name, stack in poses.items():
        assert np.allclose(stack, stack[0]) == (name in panda.static_link_names), name


def test_config_errors() -> None:
    with pytest.raises(ValueError, match="robot.urdf"):
        RobotModel.from_config(RobotConfig(urdf="/nonexistent/robot.urdf"))
    with pytest.raises(ValueError, match=r"robot.joint_names\[6\] 'nope'"):
        names = RobotConfig().joint_names[:6] + ("nope",)
        RobotModel.from_config(RobotConfig(joint_names=names))
    with pytest.raises(ValueError, match=r"robot.collision_links\[0\] 'panda_link8'"):
        RobotModel.from_config(RobotConfig(collision_links=("panda_link8",)))


def test_collision_links_subset_and_finger_beyond_urdf_limit() -> None:
    cfg = RobotConfig(
        fixed_joint_positions={"panda_finger_joint1": 0.065},  # joint2 follows through <mimic>
        collision_links=("panda_link5", "panda_hand", "panda_leftfinger", "panda_rightfinger"),
    )
    robot = RobotModel.from_config(cfg)
    assert robot.collision_link_names == cfg.collision_links
    poses = robot.link_poses(robot.home_position_rad)
    gap = np.linalg.norm(poses["panda_leftfinger"][:3, 3] - poses["panda_rightfinger"][:3, 3])
    assert gap == pytest.approx(0.13)


def test_primitive_shapes_hull_contains_them(tmp_path: Path) -> None:
    urdf = tmp_path / "prims.urdf"
    urdf.write_text("""<robot name="prims">
      <link name="base"><collision><origin xyz="0 0 0.1" rpy="0 0 0.3"/>
        <geometry><box size="0.2 0.1 0.3"/></geometry></collision></link>
      <link name="arm">
        <collision><origin xyz="0 0 0.2" rpy="0.5 0 0"/>
          <geometry><cylinder radius="0.05" length="0.4"/></geometry></collision>
        <collision><origin xyz="0 0 0.45"/><geometry><sphere radius="0.06"/></geometry></collision>
      </link>
      <joint name="j1" type="revolute"><parent link="base"/><child link="arm"/><origin xyz="0 0 0.25"/>
        <axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
    </robot>""")
    cfg = RobotConfig(name="prims", urdf=str(urdf), base_link="base", end_effector_link="arm", joint_names=("j1",),
                      max_velocity_rad_s=(1.0,), max_acceleration_rad_s2=(1.0,), max_jerk_rad_s3=(1.0,),
                      home_position_rad=(0.0,))
    robot = RobotModel.from_config(cfg)
    box, = robot.link_collision_shapes["base"]
    cylinder, sphere = robot.link_collision_shapes["arm"]
    assert (box.kind, cylinder.kind, sphere.kind) == ("box", "cylinder", "sphere")
    angles = np.linspace(0, 2 * np.pi, 200)
    rim = np.concatenate([np.column_stack([0.05 * np.cos(angles), 0.05 * np.sin(angles), np.full(200, z)])
                          for z in (-0.2, 0.2)])
    unit = np.random.default_rng(0).normal(size=(500, 3))
    surface = 0.06 * unit / np.linalg.norm(unit, axis=1, keepdims=True)
    corners = np.array([[x, y, z] for x in (-0.1, 0.1) for y in (-0.05, 0.05) for z in (-0.15, 0.15)])
    for shape, points in ((box, corners), (cylinder, rim), (sphere, surface)):
        in_link = points @ shape.link_from_shape[:3, :3].T + shape.link_from_shape[:3, 3]
        assert _inside_hull(shape.hull_vertices, shape.hull_triangles, in_link), shape.kind
    np.testing.assert_allclose(robot.link_poses(np.array([0.0]))["arm"][:3, 3], [0, 0, 0.25])


def test_load_mesh_ignores_line_records(tmp_path: Path) -> None:
    obj = tmp_path / "tet.obj"
    obj.write_text("mtllib missing.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nl 1 2\n"
                   "f 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    vertices, triangles = load_mesh(obj)
    assert vertices.shape == (4, 3) and triangles.shape == (4, 3)


def test_position_limit_override_replaces_urdf_limits() -> None:
    cfg = RobotConfig(position_limits_rad={"panda_joint4": (-3.1416, 0.0873)})
    robot = RobotModel.from_config(cfg)
    assert robot.upper_limits_rad[3] == pytest.approx(0.0873) and robot.lower_limits_rad[3] == pytest.approx(-3.1416)
    # Other joints keep the URDF's limits.
    urdf = RobotModel.from_config(RobotConfig())
    np.testing.assert_array_equal(np.delete(robot.upper_limits_rad, 3), np.delete(urdf.upper_limits_rad, 3))
    q = robot.home_position_rad.copy()
    q[3] = 0.05  # above the URDF's 0.0, below the override
    assert robot.check_joint_limits(q) == [] and urdf.check_joint_limits(q) != []
    with pytest.raises(ValueError, match=r"robot.position_limits_rad names 'panda_finger_joint1', which is not a planning joint"):
        RobotConfig(position_limits_rad={"panda_finger_joint1": (0.0, 0.08)})
    with pytest.raises(ValueError, match=r"robot.position_limits_rad.panda_joint4: lower 0.1 must be < upper 0.0"):
        RobotConfig(position_limits_rad={"panda_joint4": (0.1, 0.0)})
    with pytest.raises(ValueError, match=r"robot.position_limits_rad.panda_joint1 must be finite"):
        RobotConfig(position_limits_rad={"panda_joint1": (float("-inf"), 1.0)})
