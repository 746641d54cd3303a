"""MeshCollisionChecker: the Panda's link meshes against primitives and themselves, and the fine path check."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from robonav.pipeline.evaluation.mesh_check import MeshCollisionChecker
from robonav.pipeline.planning.metrics import interpolate_path
from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.transforms import transform_points

from ...conftest import REPO_ROOT

DEFAULT_YAML = REPO_ROOT / "configs" / "default.yaml"
FINGERS_MBM = {"panda_finger_joint1": 0.065, "panda_finger_joint2": 0.065}
# Every MBM start is this configuration (the Panda's "ready" pose).
KNOWN_GOOD_START = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
# Found by seeded random search: panda_link5 folds back onto panda_link2 (both meshes and hulls agree).
SELF_COLLIDING = np.array([0.203, -1.225, 1.823, -3.071, -0.744, 1.763, -1.682])


@pytest.fixture(scope="module")
def mbm_panda() -> RobotModel:
    """pybullet_data's Panda as MotionBenchMaker sees it: fingers at 0.065 m, MoveIt's allowed pairs."""
    pairs = tuple(tuple(p) for p in yaml.safe_load(DEFAULT_YAML.read_text())["robot"]["allowed_collision_pairs"])
    return RobotModel.from_config(RobotConfig(fixed_joint_positions=FINGERS_MBM, allowed_collision_pairs=pairs,
                                              padding_m=0.0))


@pytest.fixture(scope="module")
def checker(mbm_panda: RobotModel) -> MeshCollisionChecker:
    return MeshCollisionChecker(mbm_panda)


def _hand_box(robot: RobotModel, q: np.ndarray, name: str = "crate") -> SceneObject:
    """A 6 cm cube centered on the hand's origin at `q`."""
    hand = robot.link_poses(q)["panda_hand"][:3, 3]
    return SceneObject(name, "box", tuple(float(v) for v in hand), size_m=(0.06, 0.06, 0.06))


def test_known_good_start_is_free(checker: MeshCollisionChecker) -> None:
    checker.set_objects([SceneObject("far", "box", (2.0, 0.0, 0.5), size_m=(0.2, 0.2, 0.2))])
    assert checker.collisions(KNOWN_GOOD_START) == []
    assert not checker.in_collision(KNOWN_GOOD_START)


def test_a_state_in_a_box_collides_and_names_the_pair(checker: MeshCollisionChecker, mbm_panda: RobotModel) -> None:
    checker.set_objects([_hand_box(mbm_panda, KNOWN_GOOD_START)])
    pairs = checker.collisions(KNOWN_GOOD_START)
    assert ("panda_hand", "crate") in pairs
    assert all(b == "crate" for _, b in pairs)
    assert checker.in_collision(KNOWN_GOOD_START)
    # The same box 20 cm to the side no longer touches.
    moved = _hand_box(mbm_panda, KNOWN_GOOD_START)
    checker.set_objects([SceneObject("crate", "box", (moved.position_m[0], moved.position_m[1] + 0.3, moved.position_m[2]),
                                     size_m=(0.06, 0.06, 0.06))])
    assert checker.collisions(KNOWN_GOOD_START) == []


def test_cylinders_spheres_and_capsules_are_checked(checker: MeshCollisionChecker, mbm_panda: RobotModel) -> None:
    hand = tuple(float(v) for v in mbm_panda.link_poses(KNOWN_GOOD_START)["panda_hand"][:3, 3])
    for obj in (SceneObject("o", "cylinder", hand, radius_m=0.02, length_m=0.05),
                SceneObject("o", "sphere", hand, radius_m=0.02),
                SceneObject("o", "capsule", hand, radius_m=0.02, length_m=0.05)):
        checker.set_objects([obj])
        assert ("panda_hand", "o") in checker.collisions(KNOWN_GOOD_START), obj.type


def test_checks_the_mesh_not_its_convex_hull(checker: MeshCollisionChecker, mbm_panda: RobotModel) -> None:
    # A point in a concave pocket of panda_link5 at the start pose: inside the link's convex hull,
    # yet a 1.5 cm ball there does not touch the mesh (found by a seeded search over the hull's box).
    point_world = np.array([0.2033, 0.0428, 0.6975])
    world_from_link = mbm_panda.link_poses(KNOWN_GOOD_START)["panda_link5"]
    point_link = transform_points(np.linalg.inv(world_from_link), point_world[None])[0]
    (shape,) = mbm_panda.link_collision_shapes["panda_link5"]
    hull_v, hull_t = shape.hull_vertices, shape.hull_triangles
    a, b, c = (hull_v[hull_t[:, k]] for k in range(3))
    normals = np.cross(b - a, c - a)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    assert np.all(np.einsum("fj,fj->f", point_link - a, normals) < -0.001), "the point must lie inside the hull"
    checker.set_objects([SceneObject("pocket", "sphere", tuple(point_world), radius_m=0.015)])
    assert checker.collisions(KNOWN_GOOD_START) == []


def test_self_collision_honours_adjacent_and_allowed_pairs(checker: MeshCollisionChecker, mbm_panda: RobotModel) -> None:
    checker.set_objects([])
    assert ("panda_link2", "panda_link5") in checker.collisions(SELF_COLLIDING)
    checked = set(checker.self_collision_pairs)
    assert not checked & set(mbm_panda.adjacent_link_pairs)
    assert not checked & {tuple(sorted(p)) for p in mbm_panda.config.allowed_collision_pairs}
    # Closed fingers touch each other: a collision unless the pair is allowed.
    closed = RobotModel.from_config(RobotConfig())
    assert ("panda_leftfinger", "panda_rightfinger") in MeshCollisionChecker(closed).collisions(KNOWN_GOOD_START)
    allowed = RobotModel.from_config(RobotConfig(allowed_collision_pairs=(("panda_rightfinger", "panda_leftfinger"),)))
    assert MeshCollisionChecker(allowed).collisions(KNOWN_GOOD_START) == []


def test_check_path_interpolates_finely_and_finds_the_first_bad_state(
    checker: MeshCollisionChecker, mbm_panda: RobotModel
) -> None:
    goal = KNOWN_GOOD_START + np.array([2.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # the hand sweeps 0.6 m
    checker.set_objects([])
    free = checker.check_path(np.vstack([KNOWN_GOOD_START, goal]), start_rad=KNOWN_GOOD_START, goal_rad=goal)
    assert free.valid and free.detail == "ok" and free.first_invalid_state is None
    assert free.states_checked == len(interpolate_path(np.vstack([KNOWN_GOOD_START, goal]), 0.01)) == 201
    # A box where the hand passes halfway: found at the right interpolated state, not at the ends.
    middle = KNOWN_GOOD_START + 0.5 * (goal - KNOWN_GOOD_START)
    checker.set_objects([_hand_box(mbm_panda, middle)])
    blocked = checker.check_path(np.vstack([KNOWN_GOOD_START, goal]))
    assert not blocked.valid and blocked.pairs and all(b == "crate" for _, b in blocked.pairs)
    assert blocked.first_invalid_state is not None and 0 < blocked.first_invalid_state < 100
    assert "in collision" in blocked.detail


def test_check_path_rejects_wrong_ends_and_limit_violations(checker: MeshCollisionChecker) -> None:
    checker.set_objects([])
    goal = KNOWN_GOOD_START + 0.1
    path = np.vstack([KNOWN_GOOD_START, goal])
    assert "does not start at the start" in checker.check_path(path, start_rad=KNOWN_GOOD_START + 0.01).detail
    assert "does not end at the goal" in checker.check_path(path, goal_rad=KNOWN_GOOD_START).detail
    beyond = KNOWN_GOOD_START.copy()
    beyond[3] = 0.2  # above panda_joint4's upper limit
    verdict = checker.check_path(np.vstack([KNOWN_GOOD_START, beyond]))
    assert not verdict.valid and "panda_joint4" in verdict.detail
    with pytest.raises(ValueError, match=r"path must have shape \(K, 7\)"):
        checker.check_path(np.zeros((2, 6)))
