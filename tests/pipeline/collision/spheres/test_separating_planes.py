"""Separating planes clear self pairs only where the link meshes are apart, and change no answer."""

from __future__ import annotations

import fcl
import numpy as np
import pytest

from robonav.pipeline.collision.fcl_shapes import link_shape_geometry
from robonav.pipeline.collision.spheres.broad_phase import SphereBroadPhase
from robonav.pipeline.collision.spheres.separating_planes import PIECES, link_pieces, link_polytope
from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.transforms import transform_points
from robonav.services.config import load_robot_file

from ....conftest import REPO_ROOT

UR5_FILE = REPO_ROOT / "configs" / "ur5.yaml"


@pytest.fixture(scope="module")
def ur5() -> RobotModel:
    try:
        return RobotModel.from_config(load_robot_file(UR5_FILE))
    except (OSError, ValueError) as exc:  # the shared robots next to the repository are missing
        pytest.skip(f"UR5 description not available: {exc}")


def test_polytope_contains_the_points_and_keeps_few_vertices() -> None:
    rng = np.random.default_rng(3)
    cloud = rng.normal(size=(3000, 3)) * (0.05, 0.02, 0.03)  # a hull with hundreds of vertices
    vertices, planes = link_polytope(cloud)
    assert len(vertices) < len(cloud) and len(vertices) <= 2 * 72
    assert np.all(cloud @ planes[:, :3].T + planes[:, 3] <= 1e-12), "every point inside every face plane"
    assert np.allclose(np.linalg.norm(planes[:, :3], axis=1), 1.0)
    small = rng.normal(size=(20, 3))
    vertices, planes = link_polytope(small)
    assert np.all(small @ planes[:, :3].T + planes[:, 3] <= 1e-9) and len(vertices) <= 20


def _mesh_objects(robot: RobotModel) -> list[fcl.CollisionObject]:
    """One FCL object per link (its only shape: the UR5's links have one each), exact geometry."""
    return [fcl.CollisionObject(link_shape_geometry(robot.link_collision_shapes[link][0])[0], fcl.Transform())
            for link in robot.collision_link_names]


def test_pieces_hold_every_triangle(ur5: RobotModel) -> None:
    shape = ur5.link_collision_shapes["upper_arm_link"][0]
    pieces = link_pieces([shape])
    assert len(pieces) == PIECES
    triangles = transform_points(shape.link_from_shape, shape.vertices)[shape.triangles]  # (T, 3, 3)
    inside = np.zeros(len(triangles), dtype=bool)
    for points in pieces:
        _, planes = link_polytope(points)
        inside |= np.all(triangles @ planes[:, :3].T + planes[:, 3] <= 1e-9, axis=(1, 2))
    assert inside.all()


def test_planes_clear_pairs_only_where_the_hulls_are_apart(ur5: RobotModel) -> None:
    pairs = CollisionWorld(ur5, padding_m=0.0, broad_phase=False).self_collision_pairs
    # No gap tables: the pieces' distances in them would clear these pairs before any plane is asked.
    with_planes = SphereBroadPhase(ur5, self_pairs=pairs, self_pair_tables=False)
    without = SphereBroadPhase(ur5, self_pairs=pairs, sphere_model=with_planes.sphere_model, separating_planes=False,
                               self_pair_tables=False)
    links = list(ur5.collision_link_names)
    meshes = _mesh_objects(ur5)
    request = fcl.DistanceRequest()
    rng = np.random.default_rng(7)
    cleared = {}
    for q in rng.uniform(ur5.lower_limits_rad, ur5.upper_limits_rad, size=(150, ur5.dof)):
        flagged_before = without.suspect_pairs(q)[2].copy()
        flagged_after, poses = with_planes.suspect_pairs(q)[2], with_planes.suspect_pairs(q)[3]
        assert not np.any(flagged_after & ~flagged_before), "planes only ever clear"
        assert with_planes.state_suspect(q) == bool(flagged_after.any())
        for p in np.flatnonzero(flagged_before & ~flagged_after):
            a, b = links.index(pairs[p][0]), links.index(pairs[p][1])
            for k in (a, b):
                pose = poses[k] @ ur5.link_collision_shapes[links[k]][0].link_from_shape
                meshes[k].setTransform(fcl.Transform(pose[:3, :3], pose[:3, 3]))
            assert fcl.distance(meshes[a], meshes[b], request, fcl.DistanceResult()) > 0, pairs[p]
            cleared[pairs[p]] = cleared.get(pairs[p], 0) + 1
    # The pair whose spheres touch everywhere although a force-torque sensor's width keeps it
    # apart, and the base plate under the shoulder housing, whose hulls touch in a third of states.
    assert cleared.get(("wrist_2_link", "fts_robotside"), 0) >= 100, cleared
    assert cleared.get(("base_link", "upper_arm_link"), 0) >= 50, cleared


@pytest.mark.parametrize("padding_m", [0.0, 0.02])
def test_world_answers_are_the_same_with_planes(ur5: RobotModel, padding_m: float) -> None:
    fast, exact = CollisionWorld(ur5, padding_m=padding_m), CollisionWorld(ur5, padding_m=padding_m, broad_phase=False)
    # Boards around the arm (its base stands 0.91 m above the world origin), one turned.
    turned = (0.0, 0.0, float(np.sin(0.3)), float(np.cos(0.3)))
    boards = [SceneObject("table", "box", (0.0, 0.6, 0.8), size_m=(1.2, 0.6, 0.04)),
              SceneObject("wall", "box", (0.55, 0.0, 1.2), turned, size_m=(0.04, 1.0, 0.8)),
              SceneObject("post", "cylinder", (-0.4, -0.4, 1.1), radius_m=0.05, length_m=0.5)]
    fast.set_objects(boards)
    exact.set_objects(boards)
    rng = np.random.default_rng(11)
    states = rng.uniform(ur5.lower_limits_rad, ur5.upper_limits_rad, size=(120, ur5.dof))
    answers = [fast.collisions(q) for q in states]
    assert answers == [exact.collisions(q) for q in states]
    assert 0 < sum(bool(a) for a in answers) < len(states)
    assert any(name in ("table", "wall") for a in answers for _, name in a)
    assert fast.sphere_self_overflag() < 0.75, "the sphere-first search stays available for the UR5"


def test_a_box_face_clears_a_link_its_spheres_reach(ur5: RobotModel) -> None:
    home = ur5.home_position_rad
    world = CollisionWorld(ur5, padding_m=0.0)
    spheres = world._broad_phase
    # A board just beyond the hull's lowest point below the wrist: the spheres reach past the hull.
    poses = ur5.link_pose_stack(home)
    links = list(ur5.collision_link_names)
    li = links.index("wrist_2_link")
    hull = ur5.link_collision_shapes["wrist_2_link"][0].hull_vertices @ poses[li, :3, :3].T + poses[li, :3, 3]
    bottom = float(hull[:, 2].min())
    center = hull.mean(axis=0)
    flagged_by_spheres = 0
    for gap in (0.002, 0.004, 0.006):
        board = SceneObject("board", "box", (center[0], center[1], bottom - gap - 0.01), size_m=(0.3, 0.3, 0.02))
        world.set_objects([board])
        objects = spheres.suspect_pairs(home)[0]
        assert not objects[li, 0], gap
        no_box_test = SphereBroadPhase(ur5, sphere_model=spheres.sphere_model, separating_planes=False)
        no_box_test.set_objects([board])
        flagged_by_spheres += bool(no_box_test.suspect_pairs(home)[0][li, 0])
        assert ("wrist_2_link", "board") not in world.collisions(home)
    assert flagged_by_spheres == 3, "the premise: the spheres alone reach the board"
