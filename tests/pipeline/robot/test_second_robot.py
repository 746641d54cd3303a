"""A second arm, the KUKA LBR iiwa (configs/iiwa.yaml): nothing in the pipeline is Panda-specific."""

from __future__ import annotations

import numpy as np
import pytest

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.planning.motion_planner import MotionPlanner, PlanProblem
from robonav.pipeline.planning.result import PlanStatus
from robonav.pipeline.robot.acm import generate_acm
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.services.config import RobonavConfig, load_config

from ...conftest import REPO_ROOT

IIWA_CONFIG = REPO_ROOT / "configs" / "iiwa.yaml"
# Hand over the table to the right of the pillar, and to its left; the straight motion sweeps through it.
START = np.array([-0.9, 0.7, 0.0, -1.0, 0.0, 1.0, 0.0])
GOAL = np.array([0.9, 0.7, 0.0, -1.0, 0.0, 1.0, 0.0])


@pytest.fixture(scope="module")
def iiwa_config() -> RobonavConfig:
    return load_config(IIWA_CONFIG)


@pytest.fixture(scope="module")
def iiwa(iiwa_config: RobonavConfig) -> RobotModel:
    return RobotModel.from_config(iiwa_config.robot)


def test_config_loads_the_iiwa(iiwa_config: RobonavConfig, iiwa: RobotModel) -> None:
    assert iiwa.joint_names == tuple(f"lbr_iiwa_joint_{i}" for i in range(1, 8))
    assert iiwa.collision_link_names == tuple(f"lbr_iiwa_link_{i}" for i in range(8))
    assert np.allclose(np.degrees(iiwa.upper_limits_rad), [170, 120, 170, 120, 170, 120, 175])
    assert np.allclose(np.degrees(iiwa.velocity_limits), [98, 98, 100, 130, 140, 180, 180], atol=0.01)
    world = CollisionWorld(iiwa)
    world.set_objects(iiwa_config.sim.objects)
    assert not world.in_collision(iiwa.home_position_rad)


def test_the_base_is_its_only_static_link(iiwa: RobotModel) -> None:
    assert iiwa.static_link_names == ("lbr_iiwa_link_0",)


def test_allowed_pairs_are_the_generated_matrix(iiwa_config: RobonavConfig, iiwa: RobotModel) -> None:
    """The config's pairs are what `generate_acm` gives with the seed and sample count it names."""
    acm = generate_acm(CollisionWorld(iiwa), rng=np.random.default_rng(0), n_samples=10000)
    assert {tuple(p) for p in iiwa_config.robot.allowed_collision_pairs} == set(acm.allowed_pairs)
    assert set(acm.pairs_with("adjacent")) == set(iiwa.adjacent_link_pairs) and len(iiwa.adjacent_link_pairs) == 7


def test_plans_around_a_box(iiwa_config: RobonavConfig, iiwa: RobotModel) -> None:
    world = CollisionWorld(iiwa)
    world.set_objects([SceneObject("pillar", "box", (0.7, 0.0, 0.45), size_m=(0.15, 0.15, 0.5))])
    resolution = iiwa_config.planner.edge_resolution_rad
    assert not world.in_collision(START) and not world.in_collision(GOAL)
    assert not world.motion_valid(START, GOAL, resolution), "the straight motion must hit the box"

    planner = MotionPlanner(iiwa, world, iiwa_config.planner)
    outcome = planner.plan(PlanProblem(start_rad=START, goals_rad=GOAL, allowed_planning_time_s=5.0, seed=1))
    assert outcome.status is PlanStatus.SUCCESS, outcome.detail
    assert outcome.path is not None
    assert np.allclose(outcome.path[0], START) and np.allclose(outcome.path[-1], GOAL)
    assert world.path_valid(outcome.path, resolution)
    assert outcome.min_clearance_m > 0.0
