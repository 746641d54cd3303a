"""CollisionWorld with the Panda: self-collision, primitive objects, octomap octrees, motions."""

from __future__ import annotations

import numpy as np
import octomap
import pytest

from robonav.pipeline.collision.world import OCCUPANCY, CollisionWorld
from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.link_geometry import grow_hull
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject

# A block just below the hand at home: the fingers reach into it when joint 1 is near 0.
BLOCK = SceneObject("block", "box", (0.307, 0.0, 0.44), size_m=(0.08, 0.08, 0.08))


def _swing(panda: RobotModel, q1: float, q2: float | None = None) -> np.ndarray:
    q = panda.home_position_rad.copy()
    q[0] = q1
    if q2 is not None:
        q[1] = q2
    return q


def _octree_binary(points: np.ndarray, resolution_m: float = 0.02) -> bytes:
    tree = octomap.OcTree(resolution_m)
    tree.insertPointCloud(np.asarray(points, dtype=np.float64), np.array([0.0, 0.0, 2.0]))
    return tree.writeBinary()


def _cube_points(center: np.ndarray, half_m: float, step_m: float = 0.01) -> np.ndarray:
    axis = np.arange(-half_m, half_m + 1e-9, step_m)
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    return grid + center


@pytest.fixture
def world(panda: RobotModel) -> CollisionWorld:
    return CollisionWorld(panda, padding_m=0.01)


def test_home_is_free_and_adjacent_pairs_ignored(panda: RobotModel, world: CollisionWorld) -> None:
    assert world.collisions(panda.home_position_rad) == []
    assert not world.in_collision(panda.home_position_rad)
    assert world.clearance_m(panda.home_position_rad) == np.inf  # empty world
    checked = set(world.self_collision_pairs)
    for pair in panda.adjacent_link_pairs:
        assert pair not in checked and pair[::-1] not in checked
    # 11 links: 55 pairs minus 10 adjacent ones.
    assert len(checked) == 45


def test_closed_fingers_collide_unless_allowed() -> None:
    closed = RobotModel.from_config(RobotConfig())
    assert CollisionWorld(closed).collisions(closed.home_position_rad) == [("panda_leftfinger", "panda_rightfinger")]
    allowed = RobotModel.from_config(RobotConfig(allowed_collision_pairs=(("panda_rightfinger", "panda_leftfinger"),)))
    world = CollisionWorld(allowed)
    assert ("panda_leftfinger", "panda_rightfinger") not in world.self_collision_pairs
    assert world.collisions(allowed.home_position_rad) == []


def test_self_collision_of_folded_arm(panda: RobotModel, world: CollisionWorld) -> None:
    # Joint 6 at its lower limit with a fully bent elbow folds the hand back onto link 5.
    q = np.array([0.0, 0.0, 0.0, -3.0, 0.0, -0.08, 0.785])
    hits = world.collisions(q)
    assert hits and all(b != OCCUPANCY and b in panda.collision_link_names for _, b in hits)
    assert world.in_collision(q)


def test_box_around_hand_names_link_and_object(panda: RobotModel, world: CollisionWorld) -> None:
    hand = panda.frame_pose(panda.home_position_rad, "panda_hand")[:3, 3]
    world.set_objects([SceneObject("cage", "box", tuple(hand), size_m=(0.3, 0.3, 0.3)),
                       SceneObject("far", "sphere", (2.0, 2.0, 2.0), radius_m=0.1)])
    hits = world.collisions(panda.home_position_rad)
    assert ("panda_hand", "cage") in hits
    assert all(obj != "far" for _, obj in hits)
    assert world.in_collision(panda.home_position_rad)
    assert world.clearance_m(panda.home_position_rad) == 0.0
    world.clear_objects()
    assert not world.in_collision(panda.home_position_rad)


def test_each_primitive_type_collides(panda: RobotModel, world: CollisionWorld) -> None:
    target = panda.frame_pose(panda.home_position_rad, "panda_grasptarget")[:3, 3]
    # The open fingers lie along world y at home: a bar along y crosses them, a bar along x
    # passes between them.
    along_y, along_x = (0.7071068, 0.0, 0.0, 0.7071068), (0.0, 0.7071068, 0.0, 0.7071068)
    for obj in (SceneObject("s", "sphere", tuple(target), radius_m=0.03),
                SceneObject("c", "cylinder", tuple(target), along_y, radius_m=0.01, length_m=0.3),
                SceneObject("k", "capsule", (target[0], target[1], 0.355), radius_m=0.02, length_m=0.3)):
        world.set_objects([obj])
        assert world.collisions(panda.home_position_rad), obj.type
    # A vertical capsule's cap reaches 2 cm beyond `length_m`; the same cylinder stays clear of the hand.
    world.set_objects([SceneObject("c", "cylinder", (target[0], target[1], 0.355), radius_m=0.02, length_m=0.3)])
    assert not world.in_collision(panda.home_position_rad)
    world.set_objects([SceneObject("c", "cylinder", tuple(target), along_x, radius_m=0.01, length_m=0.3)])
    assert not world.in_collision(panda.home_position_rad)


def test_padding_is_applied_to_world_checks(panda: RobotModel) -> None:
    exact = CollisionWorld(panda, padding_m=0.0)
    hand = panda.frame_pose(panda.home_position_rad, "panda_hand")[:3, 3]
    probe = SceneObject("probe", "sphere", (hand[0] + 0.3, hand[1], hand[2]), radius_m=0.02)
    exact.set_objects([probe])
    gap = exact.clearance_m(panda.home_position_rad)
    # Slide the probe towards the hand until it sits 5 mm from the unpadded robot (the nearest
    # points are not exactly along x, so correct a few times).
    x = hand[0] + 0.3
    for _ in range(5):
        x -= gap - 0.005
        near = SceneObject("probe", "sphere", (x, hand[1], hand[2]), radius_m=0.02)
        exact.set_objects([near])
        gap = exact.clearance_m(panda.home_position_rad)
    assert gap == pytest.approx(0.005, abs=5e-4)
    assert not exact.in_collision(panda.home_position_rad)
    padded = CollisionWorld(panda, padding_m=0.01)
    padded.set_objects([near])
    assert padded.in_collision(panda.home_position_rad)


def test_grown_hulls_cover_padding_everywhere(panda: RobotModel) -> None:
    directions = np.random.default_rng(0).normal(size=(5000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    for link, (shape,) in panda.link_collision_shapes.items():
        grown, _ = grow_hull(shape.hull_vertices, shape.hull_triangles, 0.01)
        # Support functions: the grown hull reaches at least 1 cm further in every direction.
        growth = (directions @ grown.T).max(axis=1) - (directions @ shape.hull_vertices.T).max(axis=1)
        assert growth.min() >= 0.01 - 1e-9, link
        assert growth.max() <= 0.02, link


def test_octree_near_hand_collides_far_does_not(panda: RobotModel, world: CollisionWorld) -> None:
    home = panda.home_position_rad
    target = panda.frame_pose(home, "panda_grasptarget")[:3, 3]
    world.set_octree(_octree_binary(_cube_points(target, 0.03)), 0.02)
    assert world.has_octree
    hits = world.collisions(home)
    assert hits and all(obj == OCCUPANCY for _, obj in hits)
    assert {link for link, _ in hits} & {"panda_hand", "panda_leftfinger", "panda_rightfinger"}
    world.set_octree(_octree_binary(_cube_points(np.array([1.5, 1.5, 0.5]), 0.05)), 0.02)
    assert not world.in_collision(home)
    assert 1.0 < world.clearance_m(home) < 2.5
    # An octree without any occupied cell must not collide (FCL treats an empty tree as solid).
    world.set_octree(octomap.OcTree(0.02).writeBinary(), 0.02)
    assert not world.has_octree and not world.in_collision(home)
    world.clear_octree()
    assert world.clearance_m(home) == np.inf


def test_octree_input_errors(world: CollisionWorld) -> None:
    binary = _octree_binary(np.array([[1.0, 0.0, 0.5]]))
    with pytest.raises(ValueError, match="resolution"):
        world.set_octree(binary, 0.05)
    with pytest.raises(ValueError, match="octomap binary"):
        world.set_octree(b"not an octree", 0.02)


def test_clearance_decreases_as_obstacle_approaches(panda: RobotModel, world: CollisionWorld) -> None:
    hand = panda.frame_pose(panda.home_position_rad, "panda_hand")[:3, 3]
    clearances = []
    for offset in (0.6, 0.4, 0.25, 0.15):
        world.set_objects([SceneObject("ball", "sphere", (hand[0] + offset, hand[1], hand[2]), radius_m=0.05)])
        clearances.append(world.clearance_m(panda.home_position_rad))
    assert all(a > b for a, b in zip(clearances, clearances[1:]))
    assert clearances[0] < 0.6 - 0.05  # the hand is at most `offset` from the ball center


def test_motion_through_block_invalid_around_valid(panda: RobotModel, world: CollisionWorld) -> None:
    world.set_objects([BLOCK])
    start, goal = _swing(panda, -1.0), _swing(panda, 1.0)
    assert not world.in_collision(start) and not world.in_collision(goal)
    assert world.in_collision(_swing(panda, 0.0))
    assert not world.motion_valid(start, goal, 0.02)
    lifted = np.array([start, _swing(panda, -1.0, -1.4), _swing(panda, 1.0, -1.4), goal])
    assert world.path_valid(lifted, 0.02)
    assert world.path_clearance_m(lifted, 0.02) > 0.05
    assert not world.path_valid(np.array([start, goal]), 0.02)
    assert world.path_clearance_m(np.array([start, goal]), 0.05) == 0.0


def test_sphere_first_checks_are_sound_and_exact_where_asked() -> None:
    """States and edges near the block: what the sphere-first checks call free is FCL-free;
    with `exact` everywhere they are the exact checks; without it they give up some free ones."""
    # The finger pairs allowed, as in the shipped config: open fingers' spheres touch each other.
    panda = RobotModel.from_config(RobotConfig(allowed_collision_pairs=(("panda_leftfinger", "panda_rightfinger"),
                                                                        ("panda_hand", "panda_link6"))))
    world = CollisionWorld(panda, padding_m=0.01)
    world.set_objects([BLOCK])
    rng = np.random.default_rng(5)
    states = _swing(panda, 0.0) + rng.uniform(-0.6, 0.6, size=(300, panda.dof))
    states = np.clip(states, panda.lower_limits_rad, panda.upper_limits_rad)
    exact = np.array([not world.in_collision(q) for q in states])
    never = np.array([world.state_free_by_spheres(q, lambda _q: False) for q in states])
    always = np.array([world.state_free_by_spheres(q, lambda _q: True) for q in states])
    np.testing.assert_array_equal(always, exact)
    assert np.any(never) and np.all(exact[never])  # sound
    assert np.any(exact & ~never)  # conservative: some free states are given up
    fast_free = 0
    for a in states[::3]:
        b = np.clip(a + rng.uniform(-0.15, 0.15, size=panda.dof), panda.lower_limits_rad, panda.upper_limits_rad)
        assert world.motion_free_by_spheres(a, b, 0.02, lambda _q: True) == world.motion_valid(a, b, 0.02)
        if world.motion_free_by_spheres(a, b, 0.02, lambda _q: False):
            fast_free += 1
            assert world.motion_valid(a, b, 0.02)
    assert fast_free > 0
    assert world.spheres_usable


def test_motion_checks_both_ends(panda: RobotModel, world: CollisionWorld) -> None:
    world.set_objects([BLOCK])
    blocked, free = _swing(panda, 0.0), _swing(panda, 1.0)
    # A huge resolution leaves only the two ends to check.
    assert not world.motion_valid(free, blocked, 10.0)
    assert not world.motion_valid(blocked, free, 10.0)
    assert world.motion_valid(free, free, 0.02)


@pytest.mark.parametrize("broad_phase", [True, False])
def test_motion_skips_the_states_a_coarser_check_passed(panda: RobotModel, broad_phase: bool) -> None:
    world = CollisionWorld(panda, padding_m=0.0, broad_phase=broad_phase)
    world.set_objects([BLOCK])
    free_a, free_b, blocked = _swing(panda, -1.0), _swing(panda, 1.0), _swing(panda, 0.0)
    longest = float(np.max(np.abs(free_b - free_a)))
    # Vouched for at its ends only, the segment is still checked between them: the block is there.
    assert not world.motion_valid(free_a, free_b, longest / 2, checked_rad=longest)
    # What the caller vouches for is not checked again: here, falsely, a blocked end.
    assert not world.motion_valid(free_a, blocked, 10.0)
    assert world.motion_valid(free_a, blocked, 10.0, checked_rad=10.0)
    with pytest.raises(ValueError, match="checked_rad"):
        world.motion_valid(free_a, free_b, 0.02, checked_rad=float("nan"))


def test_input_errors(panda: RobotModel, world: CollisionWorld) -> None:
    with pytest.raises(ValueError, match=r"shape \(7,\)"):
        world.in_collision(np.zeros(6))
    with pytest.raises(ValueError, match=r"q_b\[2\]"):
        world.motion_valid(panda.home_position_rad, np.array([0, 0, np.inf, 0, 0, 0, 0.0]), 0.02)
    with pytest.raises(ValueError, match="resolution_rad"):
        world.motion_valid(panda.home_position_rad, panda.home_position_rad, 0.0)
    with pytest.raises(ValueError, match=r"path\[1\]"):
        world.path_valid(np.array([panda.home_position_rad, [np.nan] * 7]), 0.02)
    with pytest.raises(ValueError, match="duplicated"):
        world.set_objects([BLOCK, BLOCK])
    with pytest.raises(ValueError, match="padding_m"):
        CollisionWorld(panda, padding_m=-0.1)


def test_touches_cubes_agrees_with_the_same_cubes_as_objects(panda: RobotModel) -> None:
    """The path guard's quick check: padded links against axis-aligned cubes, as set_objects would."""
    rng = np.random.default_rng(7)
    quick = CollisionWorld(panda, padding_m=0.02, broad_phase=False)
    reference = CollisionWorld(panda, padding_m=0.02)
    side = 0.06
    outcomes = set()
    for _ in range(40):
        q = panda.home_position_rad + rng.uniform(-0.8, 0.8, panda.dof)
        hand = panda.frame_pose(q, "panda_hand")[:3, 3]
        cubes = hand + rng.uniform(-0.25, 0.25, (5, 3))
        reference.set_objects([SceneObject(f"c{i}", "box", tuple(c), size_m=(side, side, side))
                               for i, c in enumerate(cubes)])
        expected = any(other.startswith("c") for _, other in reference.collisions(q))
        assert quick.touches_cubes(q, cubes, side) == expected
        outcomes.add(expected)
    assert outcomes == {True, False}
    assert not quick.touches_cubes(panda.home_position_rad, np.zeros((0, 3)), side)
