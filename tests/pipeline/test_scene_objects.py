"""Mesh scene objects and objects attached to the hand, in the FCL collision world."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject

HOME = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
# Triangles of an axis-aligned unit cube's surface (12, outward-facing).
CUBE_VERTICES = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
CUBE_TRIANGLES = np.array([
    [0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
    [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3],
])


def _cube_mesh(name: str, center_m: np.ndarray, side_m: float) -> SceneObject:
    return SceneObject(name, "mesh", tuple(center_m), vertices_m=CUBE_VERTICES * side_m, triangles=CUBE_TRIANGLES)


def _hand_tip(panda: RobotModel, q: np.ndarray, offset_m: float) -> np.ndarray:
    """World point `offset_m` along the hand's z axis (between the fingers) at `q`."""
    return (panda.frame_pose(q, "panda_hand") @ np.array([0.0, 0.0, offset_m, 1.0]))[:3]


@pytest.fixture
def world(panda: RobotModel) -> CollisionWorld:
    return CollisionWorld(panda)


def test_mesh_object_validation() -> None:
    mesh = _cube_mesh("cube", np.zeros(3), 0.1)
    assert mesh.vertices_m.dtype == np.float64 and not mesh.vertices_m.flags.writeable
    assert mesh == _cube_mesh("cube", np.zeros(3), 0.1) and hash(mesh) == hash(_cube_mesh("cube", np.zeros(3), 0.1))
    assert mesh != _cube_mesh("cube", np.zeros(3), 0.2)
    center, half = dataclasses.replace(mesh, vertices_m=CUBE_VERTICES * 0.1 + 1.0).local_bounds_m
    assert np.allclose(center, 1.0) and np.allclose(half, 0.05)
    with pytest.raises(ValueError, match="outside"):
        SceneObject("m", "mesh", (0, 0, 0), vertices_m=CUBE_VERTICES, triangles=CUBE_TRIANGLES + 1)
    with pytest.raises(ValueError, match="not finite"):
        SceneObject("m", "mesh", (0, 0, 0), vertices_m=np.where(CUBE_VERTICES > 0, np.nan, 0.0), triangles=CUBE_TRIANGLES)
    with pytest.raises(ValueError, match="shape"):
        SceneObject("m", "mesh", (0, 0, 0), vertices_m=CUBE_VERTICES[:, :2], triangles=CUBE_TRIANGLES)
    with pytest.raises(ValueError, match="needs vertices_m"):
        SceneObject("m", "mesh", (0, 0, 0))
    with pytest.raises(ValueError, match="mesh' only"):
        SceneObject("b", "box", (0, 0, 0), size_m=(1, 1, 1), vertices_m=CUBE_VERTICES)


def test_mesh_object_collides_and_frees(world: CollisionWorld, panda: RobotModel) -> None:
    hand = panda.frame_pose(HOME, "panda_hand")[:3, 3]
    # A 10 cm cube whose surface cuts the hand; the same cube 30 cm away is free.
    world.set_objects([_cube_mesh("cube", hand + np.array([0.05, 0.0, 0.0]), 0.1)])
    assert ("panda_hand", "cube") in world.collisions(HOME)
    world.set_objects([_cube_mesh("cube", hand + np.array([0.3, 0.0, 0.0]), 0.1)])
    assert not world.in_collision(HOME)
    assert 0.1 < world.clearance_m(HOME) < 0.3
    # The mesh's frame is offset from its vertices' center: the bounds must follow the vertices.
    offset = SceneObject("cube", "mesh", tuple(hand - np.array([1.0, 0.0, 0.0])),
                         vertices_m=CUBE_VERTICES * 0.1 + np.array([1.05, 0.0, 0.0]), triangles=CUBE_TRIANGLES)
    world.set_objects([offset])
    assert world.in_collision(HOME)


def _table_under_held_box(panda: RobotModel, world: CollisionWorld) -> tuple[SceneObject, SceneObject]:
    """A 16 cm box held 10 cm beyond the hand origin, and a table whose top the box (only) reaches."""
    tip = _hand_tip(panda, HOME, 0.10)
    held = SceneObject("held", "box", tuple(tip), size_m=(0.04, 0.04, 0.16))
    box_bottom_z = tip[2] - 0.08
    table = SceneObject("table", "box", (tip[0], tip[1], box_bottom_z - 0.05 + 0.02), size_m=(0.3, 0.3, 0.1))
    return held, table


def test_attached_box_travels_with_the_hand(world: CollisionWorld, panda: RobotModel) -> None:
    held, table = _table_under_held_box(panda, world)
    world.set_objects([table])
    assert not world.in_collision(HOME), "the table alone must not touch the robot"

    world.attach_object(held, "panda_hand", ["panda_leftfinger", "panda_rightfinger"], q=HOME)
    assert world.collisions(HOME) == [("held", "table")]
    assert world.clearance_m(HOME) == 0.0

    # Lift the arm: the box comes along, so the state is free again, and the straight motion is not.
    lifted = HOME + np.array([0.0, 0.0, 0.0, 0.4, 0.0, 0.0, 0.0])
    lift = panda.frame_pose(lifted, "panda_hand")[2, 3] - panda.frame_pose(HOME, "panda_hand")[2, 3]
    assert lift > 0.05
    assert not world.in_collision(lifted)
    assert not world.motion_valid(lifted, HOME, 0.02)
    assert np.allclose(world.attached_world_from_object("held", lifted)[:3, 3],
                       _hand_tip(panda, lifted, 0.10), atol=1e-9)

    released = world.detach_object("held", q=lifted)
    assert released is not None and np.allclose(released.position_m, _hand_tip(panda, lifted, 0.10))
    assert not world.in_collision(HOME)
    assert world.attached_objects == ()


def test_touch_links_are_respected(world: CollisionWorld, panda: RobotModel) -> None:
    # A 5 cm wide box between the fingers (open 4 cm each side) touches both fingers' hulls.
    between_fingers = SceneObject("grasped", "box", tuple(_hand_tip(panda, HOME, 0.09)), size_m=(0.12, 0.12, 0.04))
    world.attach_object(between_fingers, "panda_hand", (), q=HOME)
    pairs = world.collisions(HOME)
    assert {("grasped", "panda_leftfinger"), ("grasped", "panda_rightfinger")} <= set(pairs)
    assert all(other != "panda_hand" for _, other in pairs), "its own link is always allowed"

    world.attach_object(between_fingers, "panda_hand", ("panda_leftfinger", "panda_rightfinger"), q=HOME)
    assert not world.in_collision(HOME)
    assert [a.name for a in world.attached_objects] == ["grasped"]


def test_attached_objects_check_each_other_and_other_links(world: CollisionWorld, panda: RobotModel) -> None:
    # An object on link 2 reaching into the hand and one on the hand: they meet.
    hand = panda.frame_pose(HOME, "panda_hand")[:3, 3]
    world.attach_object(SceneObject("on_hand", "sphere", tuple(hand + [0.0, 0.0, 0.0]), radius_m=0.02),
                        "panda_hand", ("panda_leftfinger", "panda_rightfinger", "panda_link7", "panda_link6"), q=HOME)
    assert not world.in_collision(HOME)
    world.attach_object(SceneObject("on_base", "sphere", tuple(hand + [0.15, 0.0, 0.0]), radius_m=0.14),
                        "panda_link0", (), q=HOME)
    pairs = set(world.collisions(HOME))
    assert ("on_hand", "on_base") in pairs or ("on_base", "on_hand") in pairs
    assert ("on_base", "panda_hand") in pairs


def test_attach_rejects_bad_input(world: CollisionWorld, panda: RobotModel) -> None:
    box = SceneObject("b", "box", (0.5, 0.0, 0.5), size_m=(0.1, 0.1, 0.1))
    with pytest.raises(ValueError, match="not a frame"):
        world.attach_object(box, "no_such_link", q=HOME)
    with pytest.raises(ValueError, match="touch_links\\[0\\]"):
        world.attach_object(box, "panda_hand", ["nope"], q=HOME)
    with pytest.raises(ValueError, match="exactly one"):
        world.attach_object(box, "panda_hand")
    world.set_objects([box])
    with pytest.raises(ValueError, match="world object"):
        world.attach_object(box, "panda_hand", q=HOME)
    world.clear_objects()
    world.attach_object(box, "panda_link8", world_from_link=np.eye(4))  # a link without geometry
    assert np.allclose(world.attached_objects[0].link_from_object, box.world_from_object)
    with pytest.raises(ValueError, match="attached object"):
        world.set_objects([box])
    with pytest.raises(ValueError, match="no attached object"):
        world.detach_object("zzz")


def test_sim_world_builds_mesh_obstacles() -> None:
    import pybullet as p

    from robonav.pipeline.sim.world import _create_obstacle

    cid = p.connect(p.DIRECT)
    try:
        body = _create_obstacle(_cube_mesh("cube", np.array([1.0, 0.0, 0.5]), 0.2), (1.0, 0.0, 0.0, 1.0), cid)
        hit = p.rayTest([1.0, 0.0, 2.0], [1.0, 0.0, 0.0], physicsClientId=cid)[0]
        assert hit[0] == body and abs(hit[3][2] - 0.6) < 1e-6
    finally:
        p.disconnect(cid)
