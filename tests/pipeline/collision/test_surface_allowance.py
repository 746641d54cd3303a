"""A map's clearance: kept away from the anchors, shrunk toward them, never below the seen surface."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robonav.pipeline.collision.surface_allowance import TIERS
from robonav.pipeline.collision.world import OCCUPANCY, CollisionWorld
from robonav.pipeline.perception.config import PerceptionConfig
from robonav.pipeline.perception.maps.octree import OccupancyMap
from robonav.pipeline.robot.model import RobotModel

SURFACE_CELL_M = 0.005
INFLATION_M = 0.02


def _wall_points(x_m: float, center_m: np.ndarray, spacing_m: float = 0.004) -> np.ndarray:
    """A 20 x 20 cm plane of points at x = x_m, facing the hand."""
    steps = np.arange(-0.1, 0.1 + 1e-9, spacing_m)
    y, z = np.meshgrid(center_m[1] + steps, center_m[2] + steps, indexing="ij")
    return np.column_stack([np.full(y.size, x_m), y.ravel(), z.ravel()])


def _hand_front_x(panda: RobotModel, q: np.ndarray) -> float:
    """Largest world x of the hand's and fingers' hulls at `q` [m]."""
    poses = panda.link_poses(q)
    front = -math.inf
    for link in ("panda_hand", "panda_leftfinger", "panda_rightfinger"):
        vertices = panda.link_hull_vertices[link]
        pose = poses[link]
        front = max(front, float((vertices @ pose[:3, :3].T + pose[:3, 3])[:, 0].max()))
    return front


def _map_world(panda: RobotModel, points: np.ndarray, *, broad_phase: bool = True) -> CollisionWorld:
    """A world whose map is `points` seen from 1 m in front of them, inflated as perception does."""
    occupancy = OccupancyMap(PerceptionConfig(inflation_m=INFLATION_M))
    occupancy.insert(points, points.mean(axis=0) + np.array([1.0, 0.0, 0.0]))
    world = CollisionWorld(panda, padding_m=0.0, broad_phase=broad_phase)
    world.set_octree(occupancy.planning_binary(), occupancy.resolution_m, occupancy.occupied_centers_m(),
                     clearance_m=INFLATION_M, surface_m=points, surface_resolution_m=SURFACE_CELL_M)
    return world


def _wall_ahead_world(panda: RobotModel, q: np.ndarray) -> CollisionWorld:
    """A map of a wall 1.2 cm beyond the fingertips at `q`: inside the 2 cm inflation, clear of
    the seen surface."""
    target = panda.frame_pose(q, "panda_grasptarget")[:3, 3]
    return _map_world(panda, _wall_points(_hand_front_x(panda, q) + 0.012, target))


def test_goal_near_a_surface_is_free_at_the_anchor_and_blocked_away_from_it(panda: RobotModel) -> None:
    home = panda.home_position_rad
    world = _wall_ahead_world(panda, home)
    assert world.has_surface_allowance and world.map_clearance_m == INFLATION_M
    hits = world.collisions(home)
    assert hits and all(other == OCCUPANCY for _, other in hits)
    with world.anchored(home[None], 1.0):
        assert world.clearance_tier(home) == 0
        assert world.collisions(home) == [] and not world.in_collision(home)
        # Farther from the anchor the clearance comes back, tier by tier.
        away = [home + np.full(panda.dof, d / math.sqrt(panda.dof)) for d in (0.1, 0.3, 0.55, 0.8, 1.2)]
        assert [world.clearance_tier(q) for q in away] == [0, 1, 2, 3, -1]
    assert world.in_collision(home)  # the block ended: no anchors, full clearance


def test_a_goal_that_touches_the_seen_surface_stays_in_collision(panda: RobotModel) -> None:
    home = panda.home_position_rad
    target = panda.frame_pose(home, "panda_grasptarget")[:3, 3]
    world = _map_world(panda, _wall_points(_hand_front_x(panda, home) - 0.01, target))
    with world.anchored(home[None], math.inf):
        assert world.clearance_tier(home) == 0
        assert any(other == OCCUPANCY for _, other in world.collisions(home))


@pytest.mark.parametrize("broad_phase", [True, False])
def test_a_seen_voxel_without_points_is_surface_as_a_whole(panda: RobotModel, broad_phase: bool) -> None:
    """Voxels the map holds without a seen point in them (filled below a surface, completed
    support) are kept off at their faces: the points refine the voxels that have them, no more."""
    home = panda.home_position_rad
    target = panda.frame_pose(home, "panda_grasptarget")[:3, 3]
    front = _hand_front_x(panda, home)
    wall = _wall_points(front + 0.012, target)
    # A voxel holding the front of the hand, in the map but with no point of the surface in it.
    poses = panda.link_poses(home)
    hull = panda.link_hull_vertices["panda_hand"] @ poses["panda_hand"][:3, :3].T + poses["panda_hand"][:3, 3]
    filled = hull[np.argmax(hull[:, 0])] - np.array([0.002, 0.0, 0.0])
    occupancy = OccupancyMap(PerceptionConfig(inflation_m=INFLATION_M))
    occupancy.insert(np.vstack([wall, filled]), wall.mean(axis=0) + np.array([1.0, 0.0, 0.0]))
    world = CollisionWorld(panda, padding_m=0.0, broad_phase=broad_phase)
    world.set_octree(occupancy.planning_binary(), occupancy.resolution_m, occupancy.occupied_centers_m(),
                     clearance_m=INFLATION_M, surface_m=wall, surface_resolution_m=SURFACE_CELL_M)
    with world.anchored(home[None], math.inf):
        assert world.clearance_tier(home) == 0
        assert any(other == OCCUPANCY for _, other in world.collisions(home))
    # The wall alone leaves the hand free there (test_goal_near_a_surface_...): the voxel did it.
    alone = _map_world(panda, wall, broad_phase=broad_phase)
    with alone.anchored(home[None], math.inf):
        assert not alone.in_collision(home)


def test_near_surface_spheres_are_conservative(panda: RobotModel) -> None:
    """At tier 0 the spheres on the surface cells clear only states FCL clears on the surface octree."""
    home = panda.home_position_rad
    target = panda.frame_pose(home, "panda_grasptarget")[:3, 3]
    points = _wall_points(_hand_front_x(panda, home) + 0.005, target)
    fast, slow = _map_world(panda, points), _map_world(panda, points, broad_phase=False)
    states = home + np.random.default_rng(3).uniform(-0.15, 0.15, size=(120, panda.dof))
    touching = 0
    with fast.anchored(home[None], math.inf), slow.anchored(home[None], math.inf):
        for q in states:
            exact = slow.in_collision(q)
            touching += exact
            assert fast.in_collision(q) == exact
    assert 0 < touching < len(states)


def test_each_state_of_an_edge_keeps_the_clearance_of_its_own_tier(panda: RobotModel) -> None:
    """An edge leaving a goal near a surface: the broad phase checks each state at the clearance
    of its own tier (the goal at none), not at the strictest tier of its ends; the edge is free
    exactly when each of its states is."""
    home = panda.home_position_rad
    world = _wall_ahead_world(panda, home)
    broad = world._broad_phase  # noqa: SLF001
    rng = np.random.default_rng(4)
    free_edges = blocked_edges = fewer = 0
    with world.anchored(home[None], 1.0):
        anchors, radius_sq = world.tier_anchors
        assert anchors.shape == (1, panda.dof) and radius_sq == 1.0
        for length in (0.1, 0.3, 0.6, 0.9, 1.3, 1.3, 1.3):
            step = rng.normal(size=panda.dof)
            b = home + length * step / np.linalg.norm(step)
            suspects, tiers, steps = broad.edge_suspects(home, b, 0.02, anchors=anchors, anchor_radius_sq=radius_sq)
            states = [home + (b - home) * (k / steps) for k in range(steps + 1)]
            own = [world.clearance_tier(q) for q in states]
            expected = {k for k in range(steps + 1) if broad.state_suspect(states[k], tier=own[k])}
            assert set(suspects.tolist()) == expected and len(suspects) == len(expected)
            assert tiers.tolist() == [own[k] for k in suspects]
            # At the clearance of the edge's far end (the strictest), more states were flagged.
            fewer += len(expected) < sum(broad.state_suspect(q, tier=max(own, key=_strictness)) for q in states)
            free = world.motion_valid(home, b, 0.02)
            assert free == all(not world.in_collision(q) for q in states)
            free_edges += free
            blocked_edges += not free
    assert free_edges and blocked_edges and fewer
    assert world.tier_anchors == (None, 0.0)  # the block ended: every state keeps the whole clearance


def test_a_single_state_keeps_the_clearance_of_its_own_tier(panda: RobotModel) -> None:
    """One state's broad-phase check works out its tier as an edge's states do: the same tier as
    `clearance_tier`, the same verdict as the spheres at that tier, and the sphere-first check
    frees exactly the states the spheres clear."""
    home = panda.home_position_rad
    world = _wall_ahead_world(panda, home)
    broad = world._broad_phase  # noqa: SLF001
    rng = np.random.default_rng(5)
    states = home + rng.normal(size=(200, panda.dof)) * rng.uniform(0.0, 0.5, size=(200, 1))
    seen_tiers, verdicts = set(), set()
    with world.anchored(np.vstack([home, home + 0.3]), 1.0):
        anchors, radius_sq = world.tier_anchors
        for q in states:
            tier = world.clearance_tier(q)
            suspect = broad.state_suspect(q, tier=tier)
            assert broad.state_suspect_tiered(q, anchors, radius_sq) == (suspect, tier)
            assert world.state_free_by_spheres(q, lambda _: False) == (not suspect)
            seen_tiers.add(tier)
            verdicts.add(suspect)
        # A read-only, Fortran-ordered copy of the anchors gives the same answers.
        odd = np.asfortranarray(anchors)
        odd.flags.writeable = False
        assert all(broad.state_suspect_tiered(q, odd, radius_sq) == broad.state_suspect_tiered(q, anchors, radius_sq)
                   for q in states[:20])
    assert seen_tiers == {-1, 0, 1, 2, 3} and verdicts == {True, False}


def _strictness(tier: int) -> int:
    """Order of tiers by the clearance they keep (-1, far from the anchors, keeps it whole)."""
    return TIERS if tier < 0 else tier


def test_map_layer_input_errors(panda: RobotModel) -> None:
    occupancy = OccupancyMap(PerceptionConfig())
    points = _wall_points(0.9, np.array([0.9, 0.0, 0.5]))
    occupancy.insert(points, np.array([1.9, 0.0, 0.5]))
    world = CollisionWorld(panda, padding_m=0.0)
    binary, seen = occupancy.planning_binary(), occupancy.occupied_centers_m()
    with pytest.raises(ValueError, match="need seen_voxels_m"):
        world.set_octree(binary, 0.02, clearance_m=0.02)
    with pytest.raises(ValueError, match="clearance_m"):
        world.set_octree(binary, 0.02, seen, clearance_m=-0.01)
    with pytest.raises(ValueError, match="surface_resolution_m"):
        world.set_octree(binary, 0.02, seen, clearance_m=0.02, surface_m=points, surface_resolution_m=0.003)
    with pytest.raises(ValueError, match="radius_rad"):
        with world.anchored(panda.home_position_rad[None], math.nan):
            pass
    # Without a clearance the map is the octree as it is: no allowance anywhere.
    world.set_octree(binary, 0.02, seen)
    assert not world.has_surface_allowance and world.map_clearance_m == 0.0
    with world.anchored(panda.home_position_rad[None], 1.0):
        assert world.clearance_tier(panda.home_position_rad) == -1
    assert TIERS >= 2
