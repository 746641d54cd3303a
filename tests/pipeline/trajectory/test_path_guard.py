"""The path guard: blocked only by new voxels on the rest of the path, at least as cautious as the planner."""

from __future__ import annotations

import numpy as np
import pytest

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.trajectory.path_guard import PathGuard, new_voxel_count
from robonav.services.config import load_config

CFG = load_config()
ROBOT = RobotModel.from_config(CFG.robot)
HOME = ROBOT.home_position_rad
PATH = np.array([HOME, HOME + [1.0, 0.2, 0.0, 0.3, 0.0, 0.0, 0.0], HOME + [2.0, 0.3, 0.0, 0.3, 0.0, -0.2, 0.0]])


def cube_of_voxels(center: np.ndarray, size_m: float = 0.1, voxel_m: float = 0.02) -> np.ndarray:
    axis = np.arange(-size_m / 2 + voxel_m / 2, size_m / 2, voxel_m)
    return center + np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)


def blocked(guard: PathGuard, centers: np.ndarray, path: np.ndarray, q_now: np.ndarray) -> bool:
    guard.update_map(centers, 0.02)
    return guard.remaining_blocked(path, q_now)


@pytest.fixture(scope="module")
def guard() -> PathGuard:
    return PathGuard(ROBOT, padding_m=CFG.robot.padding_m, inflation_m=CFG.perception.inflation_m,
                     edge_resolution_rad=0.02)


def test_voxels_on_the_path_ahead_block_it_and_behind_do_not(guard: PathGuard) -> None:
    guard.start(None)
    on_path = ROBOT.frame_pose(PATH[2], "panda_hand")[:3, 3]
    blocking = cube_of_voxels(on_path)
    assert blocked(guard, blocking, PATH, HOME)
    assert not blocked(guard, blocking, PATH[:2], HOME)  # a path that stops short of it
    far = cube_of_voxels(np.array([-0.8, -0.8, 1.2]))
    assert not blocked(guard, far, PATH, HOME)
    start = ROBOT.frame_pose(HOME, "panda_hand")[:3, 3] + [0.0, 0.0, 0.3]
    behind = cube_of_voxels(start)  # above where the arm started: already passed
    assert not blocked(guard, behind, PATH, PATH[2])
    assert not blocked(guard, np.zeros((0, 3)), PATH, HOME)


def test_a_stop_names_the_new_voxels_that_blocked_it(guard: PathGuard) -> None:
    guard.start(None)
    blocking = cube_of_voxels(ROBOT.frame_pose(PATH[2], "panda_hand")[:3, 3])
    far = cube_of_voxels(np.array([-0.8, -0.8, 1.2]))
    assert blocked(guard, np.vstack([far, blocking]), PATH, HOME)
    named = guard.blocking_centers_m
    assert len(named) > 0 and all(np.any(np.all(np.isclose(blocking, v), axis=1)) for v in named)
    assert not blocked(guard, far, PATH, HOME) and guard.blocking_centers_m.shape == (0, 3)  # a clear path names none


def test_states_ahead_start_near_the_arm_and_end_at_the_goal(guard: PathGuard) -> None:
    q_now = PATH[0] + 0.5 * (PATH[1] - PATH[0])
    states = guard.states_ahead(PATH, q_now)
    assert np.max(np.abs(states[0] - q_now)) == pytest.approx(0.05, abs=1e-9)
    np.testing.assert_allclose(states[-1], PATH[-1])
    assert np.max(np.abs(np.diff(states, axis=0))) <= 0.02 + 1e-9


@pytest.mark.parametrize("seed", range(3))
def test_the_guard_is_at_least_as_cautious_as_the_planner(guard: PathGuard, seed: int) -> None:
    """Wherever a box's voxels make the planner's check fail, the guard blocks too. The planner
    checks the padded hulls against the inflated octree; the inflated voxels of a 10 cm cube fill
    at most the cube grown by the inflation on every side."""
    rng = np.random.default_rng(seed)
    guard.start(None)
    world = CollisionWorld(ROBOT, padding_m=CFG.robot.padding_m)
    side = 0.1 + 2 * CFG.perception.inflation_m
    checked = 0
    for k in range(12):
        center = ROBOT.frame_pose(PATH[int(rng.integers(1, 3))], "panda_hand")[:3, 3] + rng.uniform(-0.15, 0.15, 3)
        world.set_objects([SceneObject("box", "box", tuple(center), size_m=(side, side, side))])
        if not world.path_valid(PATH, 0.02):
            checked += 1
            assert blocked(guard, cube_of_voxels(center), PATH, HOME)
    assert checked > 0


def test_voxels_near_the_fat_spheres_but_clear_of_the_links_do_not_block(guard: PathGuard) -> None:
    """Covering spheres are fatter than the links; the FCL confirmation keeps that from stopping the arm."""
    guard.start(None)
    hand = ROBOT.frame_pose(PATH[2], "panda_hand")
    # Beside the fingers, in the gap between the open hand's bounding sphere and its hull.
    beside = hand[:3, 3] + hand[:3, :3] @ np.array([0.0, 0.0, 0.2])
    world = CollisionWorld(ROBOT, padding_m=CFG.robot.padding_m)
    side = 0.02 + 2 * CFG.perception.inflation_m
    spared = 0
    for offset in np.linspace(0.0, 0.15, 16):
        voxel = beside + hand[:3, :3] @ np.array([0.0, 0.0, -offset])
        world.set_objects([SceneObject("v", "box", tuple(voxel), size_m=(side, side, side))])
        guard.update_map(voxel[None], 0.02)
        exact = not world.path_valid(guard.states_ahead(PATH, HOME), 0.02)
        assert guard.remaining_blocked(PATH, HOME) == exact
        spared += guard.blocked_state(PATH, HOME, confirm=False) is not None and not exact
    assert spared > 0  # some voxels only the spheres reach


def test_only_voxels_new_since_the_plan_count(guard: PathGuard) -> None:
    on_path = ROBOT.frame_pose(PATH[2], "panda_hand")[:3, 3]
    known = cube_of_voxels(on_path)
    guard.start(known, 0.02)  # the planner saw these and (being less cautious) accepted the path
    assert not blocked(guard, known, PATH, HOME)
    arrived = ROBOT.frame_pose(PATH[1], "panda_hand")[:3, 3]
    both = np.vstack([cube_of_voxels(on_path), cube_of_voxels(arrived)])
    assert blocked(guard, both, PATH, HOME)


def test_new_voxel_count_counts_only_voxels_the_previous_map_lacks() -> None:
    voxel_m = 0.02
    before = np.array([[0.01, 0.01, 0.01], [0.03, 0.01, 0.01], [0.51, 0.21, 0.31]])
    # The same voxels (centers off by less than a voxel), one gone and two new.
    now = np.array([[0.015, 0.005, 0.01], [0.51, 0.21, 0.31], [0.07, 0.01, 0.01], [-0.01, 0.01, 0.01]])
    assert new_voxel_count(before, now, voxel_m) == 2
    assert new_voxel_count(now, now, voxel_m) == 0
    assert new_voxel_count(np.zeros((0, 3)), now, voxel_m) == 4
    with pytest.raises(ValueError, match="voxel_m"):
        new_voxel_count(before, now, 0.0)


def test_with_the_allowance_a_voxel_within_the_inflation_of_the_goal_does_not_block(guard: PathGuard) -> None:
    """The planner releases the inflation near the goal (`surface_allowance.py`); so does the guard:
    a new voxel 1 cm below the goal's padded fingers blocks with the inflation everywhere, not
    with the allowance, and a voxel on the way blocks either way."""
    poses = ROBOT.link_poses(PATH[2])
    hand = np.vstack([(vertices @ poses[link][:3, :3].T) + poses[link][:3, 3]
                      for link, vertices in ROBOT.link_hull_vertices.items() if link.startswith(("panda_hand", "panda_left",
                                                                                                  "panda_right"))])
    lowest = hand[np.argmin(hand[:, 2])]
    below = (lowest - [0.0, 0.0, CFG.robot.padding_m + 0.01 + 0.01])[None]  # its top face 1 cm off the padding
    guard.start(None)
    radius = CFG.planner.surface_allowance_rad
    assert radius > 0
    guard.update_map(below, 0.02)
    assert guard.remaining_blocked(PATH, HOME)
    assert not guard.remaining_blocked(PATH, HOME, allowance_radius_rad=radius)
    # Inside what it allows, the voxel still blocks: 5 mm below the bare fingers.
    guard.update_map((lowest - [0.0, 0.0, 0.005 + 0.01])[None], 0.02)
    assert guard.remaining_blocked(PATH, HOME, allowance_radius_rad=radius)
    on_the_way = cube_of_voxels(ROBOT.frame_pose(PATH[1], "panda_hand")[:3, 3])
    guard.update_map(on_the_way, 0.02)
    assert guard.remaining_blocked(PATH, HOME, allowance_radius_rad=radius)
