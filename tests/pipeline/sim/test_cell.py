"""A cell laid out for one arm, placed for another: shoulder and reach, points moved and scaled."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.sim.cell import CellPlacement, RobotReach, robot_reach
from robonav.pipeline.sim.scenes import ClutterConfig, clutter_scene
from robonav.pipeline.transforms import PoseSpec

from ...conftest import PANDA_TEST_CONFIG

IIWA = RobotConfig(
    name="iiwa", urdf="pybullet_data:kuka_iiwa/model.urdf", base_link="lbr_iiwa_link_0", end_effector_link="lbr_iiwa_link_7",
    joint_names=tuple(f"lbr_iiwa_joint_{i}" for i in range(1, 8)), max_velocity_rad_s=(1.7,) * 7,
    max_acceleration_rad_s2=(10.0,) * 7, max_jerk_rad_s3=(5000.0,) * 7, home_position_rad=(0.0, 0.0, 0.0, -1.2, 0.0, 1.2, 0.0))


def test_the_shoulder_is_on_the_first_axis_at_the_height_of_the_first_lifting_joint() -> None:
    panda = robot_reach(RobotModel.from_config(PANDA_TEST_CONFIG))
    np.testing.assert_allclose(panda.shoulder_m, [0.0, 0.0, 0.333], atol=1e-9)  # panda_joint2's origin
    # Upper arm 0.316 + forearm 0.384 (with its 8 cm offsets) + hand 0.107 + 0.1034: about 0.86 m.
    assert 0.8 < panda.reach_m < 0.95
    iiwa = robot_reach(RobotModel.from_config(IIWA))
    np.testing.assert_allclose(iiwa.shoulder_m, [0.0, 0.0, 0.36], atol=1e-9)
    assert robot_reach(RobotModel.from_config(IIWA)) == iiwa, "seeded: the same cell every time"


def test_a_robot_standing_elsewhere_takes_the_cell_with_it() -> None:
    # Moved and turned about the vertical (as every arm here turns its first joint).
    pose = PoseSpec((1.5, -0.5, 0.2), (0.0, 0.0, math.sin(0.5), math.cos(0.5)))
    panda = robot_reach(RobotModel.from_config(PANDA_TEST_CONFIG))
    posed = robot_reach(RobotModel.from_config(dataclasses.replace(PANDA_TEST_CONFIG, world_from_base=pose)))
    np.testing.assert_allclose(posed.shoulder_m, [1.5, -0.5, 0.533], atol=1e-9)
    assert posed.reach_m == pytest.approx(panda.reach_m, abs=1e-9)
    placement = CellPlacement(panda, posed)
    assert placement.scale == pytest.approx(1.0)
    np.testing.assert_allclose(placement.point([0.6, 0.1, 0.2]), [2.1, -0.4, 0.4], atol=1e-9)


def test_points_keep_their_place_relative_to_the_shoulder_scaled_by_reach() -> None:
    source = RobotReach((0.0, 0.0, 0.333), 0.85)
    target = RobotReach((0.1, -0.2, 1.0), 1.7)
    placement = CellPlacement(source, target)
    assert placement.scale == pytest.approx(2.0)
    np.testing.assert_allclose(placement.point(source.shoulder_m), target.shoulder_m)
    np.testing.assert_allclose(placement.point([0.55, 0.0, 0.2]), [0.1 + 1.1, -0.2, 1.0 - 0.266])
    np.testing.assert_allclose(placement.point([[0.0, 0.0, 0.333], [1.0, 0.0, 0.333]]), [[0.1, -0.2, 1.0], [2.1, -0.2, 1.0]])
    np.testing.assert_allclose(placement.xy([0.0, 0.0]), [0.1, -0.2])
    assert placement.length(0.35) == pytest.approx(0.7)
    np.testing.assert_allclose(CellPlacement(source, source).point([0.3, 0.4, 0.5]), [0.3, 0.4, 0.5])
    with pytest.raises(ValueError, match="reach > 0"):
        RobotReach((0.0, 0.0, 0.0), 0.0)


def test_clutter_keeps_clear_of_the_base_where_it_stands() -> None:
    base = (0.4, 0.3)
    config = ClutterConfig(table_center_m=(0.6, 0.3, 0.1), base_xy_m=base, keep_clear_radius_m=0.35)
    for seed in range(20):
        for obj in clutter_scene(config, np.random.default_rng(seed)).objects:
            if obj.name == "table":
                continue
            assert np.hypot(obj.position_m[0] - base[0], obj.position_m[1] - base[1]) >= 0.35 - 1e-9, obj.name
    # At the default (0, 0) the scenes are what they always were.
    default = clutter_scene(ClutterConfig(), np.random.default_rng(3))
    same = clutter_scene(ClutterConfig(base_xy_m=(0.0, 0.0)), np.random.default_rng(3))
    assert [o.position_m for o in default.objects] == [o.position_m for o in same.objects]
