"""Self-collision confirms hull contacts on the exact link shapes: a concave link's pocket is free."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.evaluation.mesh_check import MeshCollisionChecker
from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.model import RobotModel


def _box_obj(low: tuple[float, float, float], high: tuple[float, float, float], first: int) -> str:
    corners = [(x, y, z) for x in (low[0], high[0]) for y in (low[1], high[1]) for z in (low[2], high[2])]
    faces = [(1, 2, 4), (1, 4, 3), (5, 7, 8), (5, 8, 6), (1, 5, 6), (1, 6, 2), (3, 4, 8), (3, 8, 7), (1, 3, 7),
             (1, 7, 5), (2, 6, 8), (2, 8, 4)]
    return "".join(f"v {x} {y} {z}\n" for x, y, z in corners) + "".join(
        f"f {a + first} {b + first} {c + first}\n" for a, b, c in faces)


def test_a_part_in_the_pocket_of_an_l_shaped_link_is_free(tmp_path: Path) -> None:
    # An L of two bars: its hull fills the square between them, where a small cube sits.
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
    robot = RobotModel.from_config(RobotConfig(
        name="ell", urdf=str(urdf), base_link="ell", end_effector_link="cube", joint_names=("lift", "reach"),
        max_velocity_rad_s=(1.0, 1.0), max_acceleration_rad_s2=(1.0, 1.0), max_jerk_rad_s3=(1.0, 1.0),
        home_position_rad=(0.0, 0.0)))
    world, meshes = CollisionWorld(robot, padding_m=0.0), MeshCollisionChecker(robot)
    in_pocket, in_bar = np.array([0.0, 0.0]), np.array([0.0, -0.12])
    assert world.link_pairs_in_collision(in_pocket, [("cube", "ell")]) == [("cube", "ell")], "the hulls touch"
    assert not meshes.in_collision(in_pocket)
    assert not world.in_collision(in_pocket) and world.collisions(in_pocket, padded=False) == []
    assert meshes.in_collision(in_bar)
    assert world.in_collision(in_bar) and world.collisions(in_bar, padded=False) == [("ell", "cube")]
