"""Hull contacts are confirmed on the exact link shapes: a concave link's pocket is free, of other links and of obstacles."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from robonav.pipeline.collision import fcl_shapes
from robonav.pipeline.collision.fcl_shapes import link_shape_geometry
from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.evaluation.mesh_check import MeshCollisionChecker
from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject


def _box_obj(low: tuple[float, float, float], high: tuple[float, float, float], first: int) -> str:
    corners = [(x, y, z) for x in (low[0], high[0]) for y in (low[1], high[1]) for z in (low[2], high[2])]
    faces = [(1, 2, 4), (1, 4, 3), (5, 7, 8), (5, 8, 6), (1, 5, 6), (1, 6, 2), (3, 4, 8), (3, 8, 7), (1, 3, 7),
             (1, 7, 5), (2, 6, 8), (2, 8, 4)]
    return "".join(f"v {x} {y} {z}\n" for x, y, z in corners) + "".join(
        f"f {a + first} {b + first} {c + first}\n" for a, b, c in faces)


def _ell_robot(tmp_path: Path) -> RobotModel:
    """An L of two bars (its hull fills the square between them) and a small cube moved by two prismatic joints."""
    (tmp_path / "ell.obj").write_text(_box_obj((0, 0, -0.02), (0.3, 0.05, 0.02), 0)
                                      + _box_obj((0, 0.05, -0.02), (0.05, 0.3, 0.02), 8))
    urdf = tmp_path / "ell.urdf"
    urdf.write_text("""<robot name="ell">
      <link name="ell"><collision><geometry><mesh filename="ell.obj"/></geometry></collision></link>
      <link name="mast"><collision><geometry><sphere radius="0.03"/></geometry></collision></link>
      <link name="cube"><collision><geometry><box size="0.04 0.04 0.04"/></geometry></collision></link>
      <joint name="lift" type="prismatic"><parent link="ell"/><child link="mast"/><origin xyz="0 0 1"/>
        <axis xyz="0 0 1"/><limit lower="0" upper="0.1" effort="1" velocity="1"/></joint>
      <joint name="reach" type="prismatic"><parent link="mast"/><child link="cube"/><origin xyz="0.15 0.15 -1"/>
        <axis xyz="1 0 0"/><limit lower="-0.2" upper="0.2" effort="1" velocity="1"/></joint>
    </robot>""")
    return RobotModel.from_config(RobotConfig(
        name="ell", urdf=str(urdf), base_link="ell", end_effector_link="cube", joint_names=("lift", "reach"),
        max_velocity_rad_s=(1.0, 1.0), max_acceleration_rad_s2=(1.0, 1.0), max_jerk_rad_s3=(1.0, 1.0),
        home_position_rad=(0.0, 0.0)))


def test_a_part_in_the_pocket_of_an_l_shaped_link_is_free(tmp_path: Path) -> None:
    robot = _ell_robot(tmp_path)
    world, meshes = CollisionWorld(robot, padding_m=0.0), MeshCollisionChecker(robot)
    in_pocket, in_bar = np.array([0.0, 0.0]), np.array([0.0, -0.12])
    assert world.link_pairs_in_collision(in_pocket, [("cube", "ell")]) == [("cube", "ell")], "the hulls touch"
    assert not meshes.in_collision(in_pocket)
    assert not world.in_collision(in_pocket) and world.collisions(in_pocket, padded=False) == []
    assert meshes.in_collision(in_bar)
    assert world.in_collision(in_bar) and world.collisions(in_bar, padded=False) == [("ell", "cube")]


@pytest.mark.parametrize("broad_phase", [True, False])
def test_an_obstacle_in_the_pocket_of_an_l_shaped_link_is_free(tmp_path: Path, broad_phase: bool) -> None:
    robot = _ell_robot(tmp_path)
    away = np.array([0.1, 0.2])  # the mast high, the cube out of the L's square
    pocket = SceneObject("post", "box", (0.15, 0.15, 0.0), size_m=(0.04, 0.04, 0.04))
    on_bar = SceneObject("brick", "box", (0.2, 0.02, 0.0), size_m=(0.04, 0.04, 0.04))
    near_bar = SceneObject("brick", "box", (0.2, 0.085, 0.0), size_m=(0.04, 0.04, 0.04))  # 15 mm off the bar
    for padding, free, blocked in ((0.0, [pocket, near_bar], [on_bar]), (0.02, [pocket], [on_bar, near_bar])):
        world = CollisionWorld(robot, padding_m=padding, broad_phase=broad_phase)
        for obj in free:
            world.set_objects([obj])
            assert not world.in_collision(away), (padding, obj.name)
            assert world.collisions(away, padded=False) == []
        for obj in blocked:
            world.set_objects([obj])
            assert world.in_collision(away) and world.collisions(away) == [("ell", obj.name)], (padding, obj.name)
    # The premise: the L's hull reaches the post, its mesh does not.
    world.set_objects([pocket])
    world._pose(away)
    assert world._collide(world._posed_obj(0, padded=False), world._object_fcl[0])
    assert not MeshCollisionChecker(robot, [pocket]).in_collision(away)


def test_exact_geometry_is_built_once_per_shape(tmp_path: Path) -> None:
    robot = _ell_robot(tmp_path)
    shape = robot.link_collision_shapes["ell"][0]
    first = link_shape_geometry(shape)
    assert link_shape_geometry(shape) is first
    # Two worlds confirm contacts on the same BVH, and both still answer right.
    worlds = [CollisionWorld(robot, padding_m=0.0) for _ in range(2)]
    for world in worlds:
        assert world.in_collision(np.array([0.0, -0.12])) and not world.in_collision(np.array([0.0, 0.0]))


def test_a_warm_up_builds_every_exact_shape_so_a_first_contact_builds_none(tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    robot = _ell_robot(tmp_path)
    built: list[str] = []
    build = fcl_shapes._link_shape_geometry
    monkeypatch.setattr(fcl_shapes, "_link_shape_geometry", lambda shape: built.append(shape.link) or build(shape))
    world = CollisionWorld(robot, padding_m=0.0)
    world.build_exact_shapes()
    assert sorted(built) == sorted(s.link for link in robot.collision_link_names for s in robot.link_collision_shapes[link])
    world.build_exact_shapes()
    assert world.collisions(np.array([0.0, -0.12]), padded=False) == [("ell", "cube")]  # confirmed on the exact shapes
    assert len(built) == len(set(built)) == 3, "nothing was built twice or after the warm-up"
