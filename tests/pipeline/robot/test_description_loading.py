"""Robot descriptions load as written: package:// URIs, relative paths, COLLADA meshes (in metres
whatever their unit), prismatic and continuous joints, welded joints named by group states;
config errors all reported at once."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.planning.config import PlannerConfig
from robonav.pipeline.planning.motion_planner import MotionPlanner, PlanProblem
from robonav.pipeline.planning.result import PlanStatus
from robonav.pipeline.robot.config import CONTINUOUS_JOINT_RANGE_RAD, RobotConfig
from robonav.pipeline.robot.description import describe_robot
from robonav.pipeline.robot.lane_kinematics import LinkKinematics
from robonav.pipeline.robot.link_geometry import collada_unit_m, load_mesh
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject

CUBE_OBJ = "".join(f"v {x} {y} {z}\n" for x in (-0.05, 0.05) for y in (-0.05, 0.05) for z in (-0.05, 0.05)) + (
    "f 1 2 4\nf 1 4 3\nf 5 7 8\nf 5 8 6\nf 1 5 6\nf 1 6 2\nf 3 4 8\nf 3 8 7\nf 1 3 7\nf 1 7 5\nf 2 6 8\nf 2 8 4\n")

URDF = """<?xml version="1.0"?>
<robot name="slider_spinner">
  <link name="base"><collision><geometry><box size="0.3 0.3 0.1"/></geometry></collision></link>
  <link name="carriage"><collision><geometry><mesh filename="package://testpkg/meshes/cube.obj"/></geometry></collision></link>
  <link name="arm"><collision><origin xyz="0.2 0 0"/><geometry><mesh filename="meshes/bar.dae"/></geometry></collision></link>
  <link name="tool"/>
  <link name="finger"><collision><geometry><sphere radius="0.02"/></geometry></collision></link>
  <joint name="slide" type="prismatic"><parent link="base"/><child link="carriage"/><origin xyz="0 0 0.3"/>
    <axis xyz="0 0 1"/><limit lower="0.0" upper="0.5" effort="10" velocity="0.25"/></joint>
  <joint name="spin" type="continuous"><parent link="carriage"/><child link="arm"/><origin xyz="0 0 0.1"/>
    <axis xyz="0 0 1"/><limit effort="10" velocity="2.0"/></joint>
  <joint name="tool_joint" type="fixed"><parent link="arm"/><child link="tool"/><origin xyz="0.45 0 0"/></joint>
  <joint name="finger_joint" type="revolute"><parent link="tool"/><child link="finger"/><origin xyz="0.03 0 0"/>
    <axis xyz="0 1 0"/><limit lower="0.1" upper="0.5" effort="1" velocity="1"/></joint>
</robot>
"""


@pytest.fixture()
def description(tmp_path: Path) -> tuple[Path, Path]:
    """(urdf, packages folder): the URDF in desc/, its package in packages/testpkg, a COLLADA bar beside it."""
    package = tmp_path / "packages" / "testpkg" / "meshes"
    package.mkdir(parents=True)
    (package / "cube.obj").write_text(CUBE_OBJ)
    meshes = tmp_path / "desc" / "meshes"
    meshes.mkdir(parents=True)
    (meshes / "bar.dae").write_bytes(trimesh.creation.box(extents=(0.4, 0.06, 0.06)).export(file_type="dae"))
    urdf = tmp_path / "desc" / "robot.urdf"
    urdf.write_text(URDF)
    return urdf, tmp_path / "packages"


def _config(urdf: Path, **overrides: object) -> RobotConfig:
    values: dict[str, object] = dict(
        name="slider", urdf=str(urdf), base_link="base", end_effector_link="tool", joint_names=("slide", "spin"),
        max_velocity_rad_s=(0.25, 2.0), max_acceleration_rad_s2=(1.0, 8.0), max_jerk_rad_s3=(500.0, 4000.0),
        home_position_rad=(0.1, 0.0))
    values.update(overrides)
    return RobotConfig(**values)  # type: ignore[arg-type]


def test_package_uris_resolve_through_configured_paths_or_ros_package_path(
        description: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    urdf, packages = description
    monkeypatch.delenv("ROS_PACKAGE_PATH", raising=False)
    with pytest.raises(ValueError, match="package 'testpkg' not found"):
        RobotModel.from_config(_config(urdf))
    robot = RobotModel.from_config(_config(urdf, package_paths=(str(packages),)))
    assert robot.link_collision_shapes["carriage"][0].source == str(packages / "testpkg" / "meshes" / "cube.obj")
    monkeypatch.setenv("ROS_PACKAGE_PATH", str(packages))
    assert RobotModel.from_config(_config(urdf)).collision_link_names == ("base", "carriage", "arm", "finger")


def test_collada_mesh_is_read_with_its_extent(description: tuple[Path, Path]) -> None:
    urdf, packages = description
    robot = RobotModel.from_config(_config(urdf, package_paths=(str(packages),)))
    bar, = robot.link_collision_shapes["arm"]
    assert bar.source.endswith("bar.dae") and bar.kind == "mesh"
    np.testing.assert_allclose(bar.hull_vertices.min(axis=0), [0.0, -0.03, -0.03], atol=1e-6)
    np.testing.assert_allclose(bar.hull_vertices.max(axis=0), [0.4, 0.03, 0.03], atol=1e-6)


def test_collada_mesh_in_millimetres_is_read_in_metres(tmp_path: Path) -> None:
    """trimesh keeps a COLLADA file's coordinates in the file's `<unit>`; the model scales them."""
    text = trimesh.creation.box(extents=(400.0, 60.0, 60.0)).export(file_type="dae")
    text = text.decode() if isinstance(text, bytes) else text
    assert "<unit" not in text
    path = tmp_path / "bar_mm.dae"
    path.write_text(text.replace("<up_axis>", '<unit name="millimeter" meter="0.001"/><up_axis>', 1))
    assert collada_unit_m(path) == 0.001
    vertices, triangles = load_mesh(path)
    assert len(triangles) == 12
    np.testing.assert_allclose(vertices.max(axis=0) - vertices.min(axis=0), [0.4, 0.06, 0.06], atol=1e-9)
    bad = tmp_path / "bad.dae"
    bad.write_text(text.replace("<up_axis>", '<unit meter="-1"/><up_axis>', 1))
    with pytest.raises(ValueError, match="not a positive number"):
        load_mesh(bad)


def test_prismatic_and_continuous_joints_move_and_plan(description: tuple[Path, Path]) -> None:
    urdf, packages = description
    robot = RobotModel.from_config(_config(urdf, package_paths=(str(packages),),
                                           fixed_joint_positions={"finger_joint": 0.3}))
    assert robot.continuous_joint_names == ("spin",)
    np.testing.assert_allclose(robot.lower_limits_rad, [0.0, CONTINUOUS_JOINT_RANGE_RAD[0]])
    np.testing.assert_allclose(robot.upper_limits_rad, [0.5, CONTINUOUS_JOINT_RANGE_RAD[1]])
    # The prismatic joint lifts the carriage by q metres; the continuous one turns past +-pi.
    assert robot.link_poses(np.array([0.2, 0.0]))["carriage"][2, 3] == pytest.approx(0.5)
    tip = robot.frame_pose(np.array([0.0, 4.0]), "tool")[:3, 3]
    np.testing.assert_allclose(tip[:2], 0.45 * np.array([np.cos(4.0), np.sin(4.0)]), atol=1e-9)
    # The compiled kinematics of the sphere broad phase agree with Pinocchio on both joint kinds.
    kinematics = LinkKinematics.from_robot(robot)
    for q in np.random.default_rng(0).uniform(robot.lower_limits_rad, robot.upper_limits_rad, size=(20, 2)):
        np.testing.assert_allclose(kinematics.link_pose_stack(q), robot.link_pose_stack(q), atol=1e-9)

    world = CollisionWorld(robot)
    # A low post in the way of the turn from -1 to 1 rad (the short way, through 0, where it
    # stands): the carriage must rise on the prismatic joint for the arm to pass over it.
    world.set_objects([SceneObject("post", "box", (0.4, 0.0, 0.3), size_m=(0.08, 0.08, 0.4))])
    start, goal = np.array([0.1, -1.0]), np.array([0.1, 1.0])
    assert not world.in_collision(start) and not world.in_collision(goal)
    assert not world.motion_valid(start, goal, 0.02), "the straight turn must hit the post"
    planner = MotionPlanner(robot, world, PlannerConfig(edge_resolution_rad=0.02))
    outcome = planner.plan(PlanProblem(start_rad=start, goals_rad=goal, allowed_planning_time_s=5.0, seed=1))
    assert outcome.status is PlanStatus.SUCCESS, outcome.detail
    assert outcome.path is not None and world.path_valid(outcome.path, 0.02)
    # Over the post (spin 0) the carriage clears it from some lift on; the path crossed there.
    clear_from = min(h for h in np.linspace(0.0, 0.5, 101) if not world.in_collision(np.array([h, 0.0])))
    assert clear_from > start[0], "the post must block the start's lift"
    assert outcome.path[:, 0].max() >= clear_from - 0.01, "the carriage rose over the post"
    assert np.all(outcome.path >= robot.lower_limits_rad) and np.all(outcome.path <= robot.upper_limits_rad)


def test_welded_joints_may_be_held_at_zero_only(description: tuple[Path, Path]) -> None:
    urdf, packages = description
    paths = (str(packages),)
    RobotModel.from_config(_config(urdf, package_paths=paths, fixed_joint_positions={"tool_joint": 0.0}))
    with pytest.raises(ValueError, match="tool_joint is 0.2, but it is a fixed joint"):
        RobotModel.from_config(_config(urdf, package_paths=paths, fixed_joint_positions={"tool_joint": 0.2}))


def test_every_config_error_is_reported_at_once(description: tuple[Path, Path]) -> None:
    urdf, packages = description
    with pytest.raises(ValueError) as info:
        _config(urdf, max_velocity_rad_s=(1.0,), home_position_rad=(0.0, 0.0, 0.0), padding_m=-1.0)
    message = str(info.value)
    assert "3 problems" in message
    for key in ("max_velocity_rad_s has 1 values", "home_position_rad has 3 values", "padding_m must be >= 0"):
        assert key in message
    with pytest.raises(ValueError) as info:
        RobotModel.from_config(_config(urdf, package_paths=(str(packages),), joint_names=("slide", "tool_joint"),
                                       base_link="nope"))
    assert "'tool_joint' is a fixed joint" in str(info.value) and "base_link 'nope'" in str(info.value)


def test_description_without_srdf_plans_the_chain_to_the_tip(description: tuple[Path, Path]) -> None:
    urdf, packages = description
    derived = describe_robot(urdf, tip_link="tool", package_paths=(str(packages),))
    cfg = derived.config
    assert cfg.joint_names == ("slide", "spin") and cfg.base_link == "base" and cfg.end_effector_link == "tool"
    assert cfg.max_velocity_rad_s == (0.25, 2.0)
    assert cfg.max_acceleration_rad_s2 == (1.0, 8.0) and cfg.max_jerk_rad_s3 == (500.0, 4000.0)
    # 0 is outside the finger's limits [0.1, 0.5]: it is held mid-range, as MoveIt's default state.
    assert cfg.fixed_joint_positions == {"finger_joint": pytest.approx(0.3)}
    assert cfg.home_position_rad == (0.0, 0.0)
    assert any("continuous joints ['spin']" in note for note in derived.notes)
    RobotModel.from_config(cfg)
