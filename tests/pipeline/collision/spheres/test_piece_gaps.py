"""Self-pair tables raised by the convex pieces' distances: sound on the meshes, and useful."""

from __future__ import annotations

import fcl
import numpy as np
import pytest

from robonav.pipeline.collision.fcl_shapes import link_shape_geometry
from robonav.pipeline.collision.spheres.broad_phase import SphereBroadPhase
from robonav.pipeline.collision.spheres.kernels import CONTACT_EPS_M
from robonav.pipeline.collision.spheres.piece_gaps import raise_by_piece_gaps
from robonav.pipeline.collision.spheres.self_pair_tables import ROUNDING_GUARD_M, SelfPairTables, build_self_pair_tables
from robonav.pipeline.collision.spheres.separating_planes import joint_frame_pieces
from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.robot.model import RobotModel

PROVEN_M = CONTACT_EPS_M + ROUNDING_GUARD_M


@pytest.fixture(scope="module")
def tables(panda: RobotModel) -> tuple[SphereBroadPhase, SelfPairTables, SelfPairTables]:
    """The Panda's broad phase, its sphere tables, and those raised by the pieces."""
    broad = SphereBroadPhase(panda, self_pairs=CollisionWorld(panda).self_collision_pairs)
    kin = broad._kin  # noqa: SLF001
    spheres = build_self_pair_tables(kin, panda.lower_limits_rad, panda.upper_limits_rad, broad._centers_joint,  # noqa: SLF001
                                     broad._radii_self, broad._link_start, broad._self_pairs)  # noqa: SLF001
    raised = raise_by_piece_gaps(spheres, kin, broad._self_pairs, joint_frame_pieces(panda, kin), CONTACT_EPS_M)  # noqa: SLF001
    return broad, spheres, raised


def _pair(broad: SphereBroadPhase, panda: RobotModel, a: str, b: str) -> int:
    links = panda.collision_link_names
    for p, (la, lb) in enumerate(broad._self_pairs):  # noqa: SLF001
        if {links[la], links[lb]} == {a, b}:
            return p
    raise AssertionError(f"no self pair {a}-{b}")


def _cells(tables: SelfPairTables, p: int) -> np.ndarray:
    start = int(tables.offset[p])
    return tables.gap_m[start:start + int(np.prod(tables.count[p]))]


def _bound(tables: SelfPairTables, p: int, q: np.ndarray) -> float:
    flat = 0
    for d in range(2):
        if tables.slot[p, d] >= 0:
            i = int(np.floor((q[tables.slot[p, d]] - tables.low[p, d]) / tables.step[p, d] + 0.5))
            flat = flat * tables.count[p, d] + i
    return float(tables.gap_m[tables.offset[p] + flat])


def _mesh_distance(panda: RobotModel, q: np.ndarray, a: str, b: str) -> float:
    """Smallest distance between the collision geometry of links `a` and `b` at `q` (FCL) [m]."""
    links = panda.collision_link_names
    poses = panda.link_pose_stack(q)
    objects = {}
    for link in (a, b):
        objects[link] = []
        for shape in panda.link_collision_shapes[link]:
            pose = poses[links.index(link)] @ shape.link_from_shape
            objects[link].append(fcl.CollisionObject(link_shape_geometry(shape)[0], fcl.Transform(pose[:3, :3], pose[:3, 3])))
    request = fcl.DistanceRequest()
    return min(fcl.distance(x, y, request, fcl.DistanceResult()) for x in objects[a] for y in objects[b])


def test_the_pieces_prove_most_of_what_the_spheres_cannot(panda: RobotModel, tables) -> None:  # noqa: ANN001
    broad, spheres, raised = tables
    wrist = _pair(broad, panda, "panda_link5", "panda_link7")
    assert np.mean(_cells(spheres, wrist) <= PROVEN_M) > 0.5
    assert np.mean(_cells(raised, wrist) <= PROVEN_M) < 0.25
    assert np.all(_cells(raised, wrist) >= _cells(spheres, wrist))
    # Three joints apart (the third swept): the sphere bound alone.
    arm = _pair(broad, panda, "panda_link2", "panda_link5")
    np.testing.assert_array_equal(_cells(raised, arm), _cells(spheres, arm))


def test_a_raised_bound_is_below_the_meshes_distance(panda: RobotModel, tables) -> None:  # noqa: ANN001
    broad, spheres, raised = tables
    wrist = _pair(broad, panda, "panda_link5", "panda_link7")
    rng = np.random.default_rng(5)
    lower, upper = panda.lower_limits_rad, panda.upper_limits_rad
    qs = rng.uniform(lower, upper, size=(600, panda.dof))
    # Half of them with the wrist folded onto link 5, where the two links come closest.
    qs[::2, 5] = rng.uniform(lower[5], lower[5] + 0.6, size=qs[::2].shape[0])
    checked = 0
    for q in qs:
        bound = _bound(raised, wrist, q)
        if bound <= PROVEN_M or _bound(spheres, wrist, q) > PROVEN_M:
            continue
        distance = _mesh_distance(panda, q, "panda_link5", "panda_link7")
        assert distance >= bound, (q, bound, distance)
        checked += 1
    assert checked > 100
