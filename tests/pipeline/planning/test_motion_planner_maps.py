"""Planning on a perceived map: a goal next to a surface is reachable, the path keeps off what was seen."""

from __future__ import annotations

import math

import numpy as np

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.perception.config import PerceptionConfig
from robonav.pipeline.perception.maps.octree import OccupancyMap
from robonav.pipeline.planning.config import PlannerConfig
from robonav.pipeline.planning.metrics import interpolate_path
from robonav.pipeline.planning.motion_planner import MotionPlanner, PlanProblem
from robonav.pipeline.planning.result import PlanStatus
from robonav.pipeline.robot.model import RobotModel

INFLATION_M = 0.02


def _wall_world(panda: RobotModel, gap_m: float) -> CollisionWorld:
    """A 20 x 20 cm wall of points `gap_m` beyond the fingertips at home, mapped as perception does."""
    home = panda.home_position_rad
    poses = panda.link_poses(home)
    front = max(float((panda.link_hull_vertices[link] @ poses[link][:3, :3].T + poses[link][:3, 3])[:, 0].max())
                for link in ("panda_hand", "panda_leftfinger", "panda_rightfinger"))
    target = panda.frame_pose(home, "panda_grasptarget")[:3, 3]
    steps = np.arange(-0.1, 0.1 + 1e-9, 0.004)
    y, z = np.meshgrid(target[1] + steps, target[2] + steps, indexing="ij")
    points = np.column_stack([np.full(y.size, front + gap_m), y.ravel(), z.ravel()])
    occupancy = OccupancyMap(PerceptionConfig(inflation_m=INFLATION_M))
    occupancy.insert(points, points.mean(axis=0) + np.array([1.0, 0.0, 0.0]))
    world = CollisionWorld(panda, padding_m=0.0)
    world.set_octree(occupancy.planning_binary(), occupancy.resolution_m, occupancy.occupied_centers_m(),
                     clearance_m=INFLATION_M, surface_m=points, surface_resolution_m=0.005)
    return world


def _problem(panda: RobotModel) -> PlanProblem:
    start = panda.home_position_rad.copy()
    start[0] += 1.0  # the hand swung a metre-radian to the side, far from the wall
    return PlanProblem(start_rad=start, goals_rad=panda.home_position_rad, planner_id="rrtconnect",
                       allowed_planning_time_s=5.0, seed=2)


def test_goal_inside_the_inflation_is_planned_to_and_the_path_keeps_off_the_surface(panda: RobotModel) -> None:
    world = _wall_world(panda, gap_m=0.012)
    goal = panda.home_position_rad
    assert world.in_collision(goal)  # inside the clearance, as the inflated map has it
    outcome = MotionPlanner(panda, world, PlannerConfig(seed=2)).plan(_problem(panda))
    assert outcome.status is PlanStatus.SUCCESS, outcome.detail
    assert np.allclose(outcome.path[-1], goal)
    # Every state keeps the padded links off the seen surface; away from the goal, the clearance holds.
    with world.anchored(goal[None], math.inf):
        assert not any(world.in_collision(q) for q in interpolate_path(outcome.path, 0.01))
    far = [q for q in interpolate_path(outcome.path, 0.05) if np.linalg.norm(q - goal) >= 1.0
           and np.linalg.norm(q - outcome.path[0]) >= 1.0]
    assert all(not world.in_collision(q) for q in far)


def test_without_the_allowance_the_inflation_swallows_the_goal(panda: RobotModel) -> None:
    world = _wall_world(panda, gap_m=0.012)
    outcome = MotionPlanner(panda, world, PlannerConfig(surface_allowance_rad=0.0, seed=2)).plan(_problem(panda))
    assert outcome.status is PlanStatus.GOAL_INVALID
    assert "occupancy" in outcome.detail


def test_a_goal_touching_the_seen_surface_is_in_collision(panda: RobotModel) -> None:
    world = _wall_world(panda, gap_m=-0.01)
    outcome = MotionPlanner(panda, world, PlannerConfig(seed=2)).plan(_problem(panda))
    assert outcome.status is PlanStatus.GOAL_INVALID
    assert "goal is in collision" in outcome.detail and "occupancy" in outcome.detail
