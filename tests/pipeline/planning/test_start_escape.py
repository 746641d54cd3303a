"""Leaving a start inside the padding around the occupancy map (MoveIt's FixStartStateCollision, checked)."""

from __future__ import annotations

import dataclasses

import numpy as np
import octomap
import pytest

from robonav.pipeline.collision.world import OCCUPANCY, CollisionWorld
from robonav.pipeline.planning.config import PlannerConfig
from robonav.pipeline.planning.metrics import interpolate_path
from robonav.pipeline.planning.motion_planner import MotionPlanner, PlanProblem
from robonav.pipeline.planning.result import PlanStatus
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject

PADDING_M = 0.05
VOXEL_M = 0.02
RESOLUTION_RAD = 0.02


def _slab_below_hand(robot: RobotModel, q: np.ndarray, top_z_m: float) -> bytes:
    """An octomap of a 12 x 12 cm slab, two voxels thick, whose top is near `top_z_m`, under the hand."""
    hand = robot.frame_pose(q, "panda_hand")[:3, 3]
    axis = np.arange(-0.06, 0.061, 0.01)
    xy = np.stack(np.meshgrid(axis, axis, indexing="ij"), axis=-1).reshape(-1, 2) + hand[:2]
    points = np.vstack([np.column_stack([xy, np.full(len(xy), top_z_m - dz)]) for dz in (0.005, 0.025)])
    tree = octomap.OcTree(VOXEL_M)
    tree.insertPointCloud(points, np.array([hand[0], hand[1], 2.0]))
    return tree.writeBinary()


@pytest.fixture(scope="module")
def start(panda: RobotModel) -> np.ndarray:
    q = panda.home_position_rad.copy()
    q[0] = -1.0
    return q


def _world_with_gap(panda: RobotModel, start: np.ndarray, low_m: float, high_m: float) -> CollisionWorld:
    """A world whose slab leaves the bare links between `low_m` and `high_m` from it at `start`."""
    world = CollisionWorld(panda, padding_m=PADDING_M)
    lowest = min(panda.frame_pose(start, link)[2, 3] for link in ("panda_leftfinger", "panda_rightfinger"))
    for top in np.arange(lowest, lowest - 0.2, -0.005):
        world.set_octree(_slab_below_hand(panda, start, float(top)), VOXEL_M)
        clearance = world.clearance_m(start)
        if low_m < clearance < high_m:
            return world
    raise AssertionError(f"no slab height leaves a gap in ({low_m}, {high_m})")


def _planner(panda: RobotModel, world: CollisionWorld, **config: float) -> MotionPlanner:
    return MotionPlanner(panda, world, PlannerConfig(edge_resolution_rad=RESOLUTION_RAD, range_rad=1.0, **config))


def test_a_start_inside_the_padding_is_left_through_states_with_bare_links_clear(panda, start) -> None:
    world = _world_with_gap(panda, start, 0.005, PADDING_M - 0.01)
    assert world.collisions(start) and all(other == OCCUPANCY for _, other in world.collisions(start))
    goal = start.copy()
    goal[0] = 1.0
    outcome = _planner(panda, world).plan(PlanProblem(start, goal, allowed_planning_time_s=5.0, seed=2))
    assert outcome.status is PlanStatus.SUCCESS, outcome.detail
    path = outcome.path
    np.testing.assert_array_equal(path[0], start)
    np.testing.assert_array_equal(path[-1], goal)
    escape = outcome.start_escape
    assert escape is not None
    np.testing.assert_array_equal(escape.from_rad, start)
    np.testing.assert_array_equal(escape.to_rad, path[1])
    assert escape.pairs and float(np.max(np.abs(path[1] - start))) <= 0.1 + 1e-12
    # The way out keeps the bare links clear; from the escape state on, the padded robot is clear.
    assert not any(world.collisions(q, padded=False) for q in interpolate_path(path[:2], RESOLUTION_RAD / 4))
    assert world.path_valid(path[1:], RESOLUTION_RAD)
    assert outcome.path_length_rad > float(np.max(np.abs(path[1] - start)))


def test_escaping_is_reproducible_and_can_be_switched_off(panda, start) -> None:
    world = _world_with_gap(panda, start, 0.005, PADDING_M - 0.01)
    goal = start.copy()
    goal[0] = 1.0
    first, second = (_planner(panda, world).plan(PlanProblem(start, goal, allowed_planning_time_s=5.0, seed=3))
                     for _ in range(2))
    np.testing.assert_array_equal(first.start_escape.to_rad, second.start_escape.to_rad)
    off = _planner(panda, world, start_escape_rad=0.0).plan(PlanProblem(start, goal, seed=3))
    assert off.status is PlanStatus.START_INVALID and "occupancy" in off.detail


def test_bare_links_touching_the_map_or_an_object_are_still_start_in_collision(panda, start) -> None:
    touching = _world_with_gap(panda, start, -1.0, 1e-9)  # clearance 0: a bare link reaches a voxel
    goal = start.copy()
    goal[0] = 1.0
    outcome = _planner(panda, touching).plan(PlanProblem(start, goal, seed=1))
    assert outcome.status is PlanStatus.START_INVALID

    world = CollisionWorld(panda, padding_m=PADDING_M)
    hand = panda.frame_pose(start, "panda_hand")[:3, 3]
    for top in np.arange(hand[2], hand[2] - 0.3, -0.005):  # a box top 0.5-4 cm below the fingers
        world.set_objects([SceneObject("near", "box", (hand[0], hand[1], top - 0.05), size_m=(0.12, 0.12, 0.1))])
        if 0.005 < world.clearance_m(start) < PADDING_M - 0.01:
            break
    assert world.collisions(start) and not world.collisions(start, padded=False)
    outcome = _planner(panda, world).plan(PlanProblem(start, goal, seed=1))
    assert outcome.status is PlanStatus.START_INVALID and outcome.details["pairs"]


def test_config_rejects_negative_escape_settings() -> None:
    with pytest.raises(ValueError, match="start_escape_rad"):
        PlannerConfig(start_escape_rad=-0.1)
    with pytest.raises(ValueError, match="start_escape_samples"):
        dataclasses.replace(PlannerConfig(), start_escape_samples=-1)


def _voxel_box(low_m: np.ndarray, high_m: np.ndarray) -> np.ndarray:
    """Centers of the VOXEL_M grid cells whose centers lie in [low_m, high_m]."""
    axes = [np.arange(np.ceil(lo / VOXEL_M - 0.5), np.floor(hi / VOXEL_M - 0.5) + 1) * VOXEL_M + VOXEL_M / 2
            for lo, hi in zip(low_m, high_m)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def _octree(centers_m: np.ndarray) -> bytes:
    tree = octomap.OcTree(VOXEL_M)
    for center in centers_m:
        tree.updateNode(center, True)
    return tree.writeBinary()


def test_a_hand_inside_the_inflation_but_a_padding_off_what_was_seen_escapes(panda, start) -> None:
    """After a guard stop the bare hand rests inside the inflated map, a padding away from the
    seen voxels: with those known it leaves; judged on the inflated map alone it stays stuck."""
    padding_m, inflation_m = 0.01, 2 * VOXEL_M
    hand = panda.frame_pose(start, "panda_hand")[:3, 3]
    lowest = min(panda.frame_pose(start, link)[2, 3] for link in ("panda_leftfinger", "panda_rightfinger"))
    goal = start.copy()
    goal[0] = 1.0
    for top in np.arange(lowest, lowest - 0.2, -VOXEL_M / 4):
        seen = _voxel_box(hand - [0.06, 0.06, 0.0] + [0, 0, top - hand[2] - 2 * VOXEL_M],
                          hand + [0.06, 0.06, 0.0] + [0, 0, top - hand[2]])
        grown = _voxel_box(seen.min(axis=0) - inflation_m, seen.max(axis=0) + inflation_m)
        world = CollisionWorld(panda, padding_m=padding_m)
        world.set_octree(_octree(grown), VOXEL_M, seen)
        if world.collisions(start, padded=False) and not world.touches_cubes(start, seen, VOXEL_M):
            break
    else:
        raise AssertionError("no slab height puts the bare hand in the inflation only")
    outcome = _planner(panda, world).plan(PlanProblem(start, goal, allowed_planning_time_s=5.0, seed=2))
    assert outcome.status is PlanStatus.SUCCESS, outcome.detail
    path = outcome.path
    np.testing.assert_array_equal(path[0], start)
    assert not any(world.touches_cubes(q, seen, VOXEL_M) for q in interpolate_path(path[:2], RESOLUTION_RAD / 4))
    assert world.path_valid(path[1:], RESOLUTION_RAD)

    unknown = CollisionWorld(panda, padding_m=padding_m)
    unknown.set_octree(_octree(grown), VOXEL_M)
    assert unknown.seen_voxels_m is None
    stuck = _planner(panda, unknown).plan(PlanProblem(start, goal, allowed_planning_time_s=5.0, seed=2))
    assert stuck.status is PlanStatus.START_INVALID and "occupancy" in stuck.detail


def test_seen_voxels_must_be_finite_triples(panda) -> None:
    world = CollisionWorld(panda, padding_m=0.01)
    binary = _octree(np.array([[1.0, 1.0, 1.0]]))
    with pytest.raises(ValueError, match="seen_voxels_m"):
        world.set_octree(binary, VOXEL_M, np.zeros((3, 2)))
    with pytest.raises(ValueError, match="seen_voxels_m"):
        world.set_octree(binary, VOXEL_M, np.array([[np.nan, 0.0, 0.0]]))
    world.set_octree(binary, VOXEL_M, np.array([[1.01, 1.01, 1.01]]))
    assert world.seen_voxels_m.shape == (1, 3) and world.octree_resolution_m == VOXEL_M
    with pytest.raises(ValueError, match="octomap binary"):
        world.set_octree(b"not a map", VOXEL_M, np.zeros((5, 3)))
    assert world.seen_voxels_m.shape == (1, 3)  # a refused map changes nothing
    world.clear_octree()
    assert world.seen_voxels_m is None and world.octree_resolution_m == 0.0
