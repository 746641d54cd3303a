"""Sphere broad phase: conservative against FCL, same CollisionWorld answers with and without it."""

from __future__ import annotations

import json

import numpy as np
import octomap
import pytest

from robonav.pipeline.collision.edges import bisection_order
from robonav.pipeline.collision.spheres.broad_phase import SphereBroadPhase
from robonav.pipeline.collision.spheres.sphere_model import padded_growth_m
from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.link_geometry import grow_hull
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject

from ....conftest import MBM_DIR

MBM_BOX = MBM_DIR / "box.json"
"""The shared MotionBenchMaker data next to the repository (or where ROBONAV_MBM_DIR points)."""


@pytest.fixture(scope="module")
def panda() -> RobotModel:
    """Open fingers; finger-finger and hand-link6 allowed as in MBM (their spheres, unlike their hulls, touch at home)."""
    return RobotModel.from_config(RobotConfig(
        fixed_joint_positions={"panda_finger_joint1": 0.04, "panda_finger_joint2": 0.04},
        allowed_collision_pairs=(("panda_leftfinger", "panda_rightfinger"), ("panda_hand", "panda_link6"))))


def _mbm_like_scene() -> list[SceneObject]:
    """Problem 1 of MBM's `box` family when the benchmark is present, else a similar hand-made clutter."""
    if MBM_BOX.is_file():
        raw = json.loads(MBM_BOX.read_text())["problems"][0]["obstacles"]
        return [SceneObject(o["name"], o["type"], tuple(o["position"]), tuple(o["orientation_xyzw"]),
                            size_m=tuple(o["size"]) if o["type"] == "box" else None,
                            radius_m=o.get("radius"), length_m=o.get("length")) for o in raw]
    return [SceneObject("floor", "box", (0.5, 0.0, -0.02), size_m=(0.6, 0.8, 0.04)),
            SceneObject("back", "box", (0.8, 0.0, 0.3), size_m=(0.04, 0.8, 0.6)),
            SceneObject("side", "box", (0.5, 0.4, 0.3), (0.0, 0.0, 0.38, 0.92), size_m=(0.6, 0.04, 0.6)),
            SceneObject("can", "cylinder", (0.5, -0.1, 0.1), radius_m=0.04, length_m=0.2)]


def _clutter() -> list[SceneObject]:
    return [*_mbm_like_scene(),
            SceneObject("ball", "sphere", (0.3, 0.3, 0.5), radius_m=0.08),
            SceneObject("pill", "capsule", (0.2, -0.4, 0.4), (0.3, 0.0, 0.0, 0.95), radius_m=0.05, length_m=0.3)]


@pytest.fixture(scope="module")
def worlds(panda: RobotModel) -> tuple[CollisionWorld, CollisionWorld]:
    fast, slow = CollisionWorld(panda, padding_m=0.01), CollisionWorld(panda, padding_m=0.01, broad_phase=False)
    for world in (fast, slow):
        world.set_objects(_clutter())
    return fast, slow


def _random_states(robot: RobotModel, count: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(robot.lower_limits_rad, robot.upper_limits_rad, size=(count, robot.dof))


def test_suspect_whenever_fcl_collides(panda: RobotModel, worlds: tuple[CollisionWorld, CollisionWorld]) -> None:
    fast, slow = worlds
    broad = fast._broad_phase  # noqa: SLF001 (the world's own broad phase)
    qs = _random_states(panda, 1500, seed=10)
    colliding = np.array([slow.in_collision(q) for q in qs])
    suspect = np.array([broad.state_suspect(q) for q in qs])
    assert colliding.any() and (~colliding).any()
    assert not np.any(colliding & ~suspect)
    assert (~suspect).any()  # it clears something


def test_same_answers_with_and_without_broad_phase(panda: RobotModel,
                                                   worlds: tuple[CollisionWorld, CollisionWorld]) -> None:
    fast, slow = worlds
    qs = _random_states(panda, 2000, seed=11)
    assert [fast.in_collision(q) for q in qs] == [slow.in_collision(q) for q in qs]
    rng = np.random.default_rng(12)
    free = [q for q in qs if not slow.in_collision(q)][:300]
    edges = []
    for q in free:
        step = rng.normal(size=panda.dof)
        edges.append((q, np.clip(q + 0.6 * step / np.abs(step).max(), panda.lower_limits_rad, panda.upper_limits_rad)))
    fast_answers = [fast.motion_valid(a, b, 0.02) for a, b in edges]
    assert fast_answers == [slow.motion_valid(a, b, 0.02) for a, b in edges]
    assert any(fast_answers) and not all(fast_answers)


def test_fcl_asked_only_of_pairs_whose_spheres_touch(panda: RobotModel) -> None:
    """`collisions` lists the same pairs when FCL is asked only about the pairs the spheres flag,
    objects and occupied voxels together; the flags come with the links' poses."""
    fast, slow = CollisionWorld(panda, padding_m=0.01), CollisionWorld(panda, padding_m=0.01, broad_phase=False)
    slab = np.stack(np.meshgrid(np.arange(-0.6, -0.4, 0.02), np.arange(-0.3, 0.3, 0.02), np.arange(0.0, 0.8, 0.02),
                                indexing="ij"), axis=-1).reshape(-1, 3)
    binary = _octree_binary(slab, 0.02)
    for world in (fast, slow):
        world.set_objects(_clutter())
        world.set_octree(binary, 0.02)
    broad = fast._broad_phase  # noqa: SLF001
    qs = _random_states(panda, 600, seed=19)
    kinds = set()
    for q in qs:
        expected = slow.collisions(q)
        assert fast.collisions(q) == expected
        kinds |= {"self" if b in panda.collision_link_names else b for _, b in expected}
        objects, voxels, pairs, poses = broad.suspect_pairs(q)
        np.testing.assert_allclose(poses, panda.link_pose_stack(q), atol=1e-9)
        assert bool(objects.any() or voxels.any() or pairs.any()) == broad.state_suspect(q)
    assert {"self", "occupancy"} <= kinds and len(kinds) >= 4


def test_edge_visits_states_in_motion_valid_order(panda: RobotModel) -> None:
    broad = SphereBroadPhase(panda)
    # A box around the whole robot: every state is suspect, so the order is visible.
    broad.set_objects([SceneObject("all", "box", (0.0, 0.0, 0.5), size_m=(3.0, 3.0, 3.0))])
    a, b = panda.home_position_rad, panda.home_position_rad + 0.37
    suspects, tiers, steps = broad.edge_suspects(a, b, 0.01)
    assert steps == 37 and tiers is None  # no anchors: every state at the default tier
    assert suspects.tolist() == [37, *bisection_order(37), 0]
    first, _, _ = broad.edge_suspects(a, b, 0.01, first_only=True)
    assert first.tolist() == [37]
    # Passed at 0.02 rad (19 steps): of the 37 steps at 0.01 rad only the ends are among its states.
    suspects, _, steps = broad.edge_suspects(a, b, 0.01, checked_rad=0.02)
    assert steps == 37 and suspects.tolist() == [k for k in (37, *bisection_order(37), 0) if k % 37]
    assert broad.edge_suspects(a, b, 0.01, checked_rad=0.01)[0].size == 0  # all of them known
    # 0.375 rad at 1/16 rad (6 steps) after 1/8 rad (3 steps): every second state is known.
    suspects, _, steps = broad.edge_suspects(a, a + 0.375, 0.0625, checked_rad=0.125)
    assert steps == 6 and suspects.tolist() == [k for k in (6, *bisection_order(6), 0) if k % 2]
    broad.clear_objects()
    assert broad.edge_suspects(a, b, 0.01)[0].size == 0
    assert not broad.state_suspect(panda.home_position_rad)


def test_first_only_finds_a_suspect_of_the_edge(panda: RobotModel,
                                                worlds: tuple[CollisionWorld, CollisionWorld]) -> None:
    broad = worlds[0]._broad_phase  # noqa: SLF001
    rng = np.random.default_rng(23)
    starts = _random_states(panda, 300, seed=24)
    blocked = not_first = 0
    for a in starts:
        b = np.clip(a + rng.uniform(-0.6, 0.6, size=panda.dof), panda.lower_limits_rad, panda.upper_limits_rad)
        every, _, steps = broad.edge_suspects(a, b, 0.01)
        first, _, first_steps = broad.edge_suspects(a, b, 0.01, first_only=True)
        assert first_steps == steps and first.size == min(every.size, 1)
        if first.size:
            # One of the edge's suspects, from its first chunk (16 states) that holds one.
            order = [steps, *bisection_order(steps), 0]
            assert first[0] in every and order.index(first[0]) // 16 == order.index(every[0]) // 16
            blocked += 1
            not_first += first[0] != every[0]
    assert blocked > 20 and not_first > 0  # the search stops at a chunk's first flag, not its lane 0


def test_attached_spheres(panda: RobotModel) -> None:
    broad = SphereBroadPhase(panda, padding_m=0.0)
    home = panda.home_position_rad
    hand = panda.frame_pose(home, "panda_hand")
    probe_world = hand[:3, 3] + hand[:3, 2] * 0.30  # 30 cm beyond the hand along its z axis
    broad.set_objects([SceneObject("probe", "sphere", tuple(probe_world), radius_m=0.03)])
    assert not broad.state_suspect(home)
    # A 10 cm rod held by the hand (link frame), ending close to the probe.
    centers = np.array([[0.0, 0.0, 0.1 + 0.04 * i] for i in range(5)])
    broad.set_attached_spheres("rod", "panda_hand", centers, np.full(5, 0.03),
                               touch_links=("panda_leftfinger", "panda_rightfinger"))
    assert broad.state_suspect(home)
    broad.clear_objects()
    assert not broad.state_suspect(home)  # own link and touch links are ignored
    broad.set_attached_spheres("rod", "panda_hand", centers, np.full(5, 0.03))
    assert broad.state_suspect(home)  # now the fingers count
    broad.remove_attached("rod")
    assert not broad.state_suspect(home)


def _octree_binary(points: np.ndarray, resolution_m: float) -> bytes:
    tree = octomap.OcTree(resolution_m)
    tree.updateNodes(np.asarray(points, dtype=np.float64), True, lazy_eval=True)
    tree.updateInnerOccupancy()
    return tree.writeBinary()


def test_voxels_conservative_and_world_answers_equal(panda: RobotModel) -> None:
    rng = np.random.default_rng(13)
    target = panda.frame_pose(panda.home_position_rad, "panda_grasptarget")[:3, 3]
    # A slab of voxels in front of the robot and a cube around the grasp target at home.
    slab = np.stack(np.meshgrid(np.arange(0.45, 0.6, 0.02), np.arange(-0.3, 0.3, 0.02), np.arange(0.0, 0.8, 0.02),
                                indexing="ij"), axis=-1).reshape(-1, 3)
    cube = target + rng.uniform(-0.04, 0.04, size=(100, 3))
    binary = _octree_binary(np.vstack([slab, cube]), 0.02)
    fast, slow = CollisionWorld(panda, padding_m=0.01), CollisionWorld(panda, padding_m=0.01, broad_phase=False)
    for world in (fast, slow):
        world.set_octree(binary, 0.02)
    assert slow.in_collision(panda.home_position_rad) and fast.in_collision(panda.home_position_rad)
    qs = _random_states(panda, 300, seed=14)
    slow_answers = [slow.in_collision(q) for q in qs]
    assert any(slow_answers) and not all(slow_answers)
    assert [fast.in_collision(q) for q in qs] == slow_answers
    broad = fast._broad_phase  # noqa: SLF001
    assert all(broad.state_suspect(q) for q, hit in zip(qs, slow_answers) if hit)
    assert all(broad.clearance_pair_bounds_m(q)[0].min() <= slow.clearance_m(q) + 1e-9 for q in qs[:40])
    # States go through in lanes of 16: the same bounds as one at a time, voxels included.
    bounds, poses = broad.clearance_pair_bounds_m(qs[:40])
    assert np.array_equal(bounds, np.concatenate([broad.clearance_pair_bounds_m(q)[0] for q in qs[:40]]))
    assert np.array_equal(poses, np.concatenate([broad.clearance_pair_bounds_m(q)[1] for q in qs[:40]]))
    assert np.isfinite(bounds[..., -1]).all()
    fast.clear_octree()
    assert not fast.in_collision(panda.home_position_rad)
    assert not broad.state_suspect(panda.home_position_rad)


def test_clearance_lower_bound_and_min_clearance(panda: RobotModel,
                                                  worlds: tuple[CollisionWorld, CollisionWorld]) -> None:
    """The spheres' bound never exceeds FCL's distance from the bare hulls, and the
    bound-ordered minimum over states and pairs equals the plain minimum with far fewer FCL
    queries."""
    fast, slow = worlds
    broad = fast._broad_phase  # noqa: SLF001
    qs = _random_states(panda, 200, seed=15)
    exact = np.array([slow.clearance_m(q) for q in qs])
    bounds = np.array([broad.clearance_pair_bounds_m(q)[0].min() for q in qs])
    assert np.all(bounds <= exact + 1e-9)
    assert np.array_equal(broad.clearance_pair_bounds_m(qs)[0].min(axis=(1, 2)), bounds)  # lanes of 16 states
    assert np.any(exact > 0) and np.median(exact - bounds) < 0.05  # a bound, and a useful one
    queries = {"fast": 0, "slow": 0}
    for name, world in (("fast", fast), ("slow", slow)):
        original = world._distance  # noqa: SLF001 (counting FCL distance queries)
        world._distance = lambda a, b, name=name, original=original: (  # type: ignore[method-assign]
            queries.__setitem__(name, queries[name] + 1) or original(a, b))
    try:
        for chunk in np.array_split(qs, 10):
            assert fast.min_clearance_m(chunk) == pytest.approx(min(slow.clearance_m(q) for q in chunk), abs=1e-9)
        for q in qs[:20]:
            assert fast.clearance_m(q) == pytest.approx(slow.clearance_m(q), abs=1e-9)
    finally:
        del fast._distance, slow._distance
    # Triples in bound order: a handful of FCL queries per chunk of 20 states, not one per near pair.
    assert queries["fast"] < queries["slow"] / 10
    path = qs[:3]
    assert fast.path_clearance_m(path, 0.2) == slow.path_clearance_m(path, 0.2)
    assert SphereBroadPhase(panda).clearance_pair_bounds_m(panda.home_position_rad)[0].min() == np.inf  # empty world


def test_edge_suspects_are_the_suspect_states_of_the_edge(panda: RobotModel,
                                                          worlds: tuple[CollisionWorld, CollisionWorld]) -> None:
    """The edge loop takes each state's joint cosines and sines by a rotation per step; its
    suspects are exactly the states `state_suspect` flags, on edges of up to ~300 steps."""
    broad = worlds[0]._broad_phase  # noqa: SLF001
    rng = np.random.default_rng(16)
    starts = _random_states(panda, 40, seed=17)
    flagged = 0
    for a in starts:
        b = np.clip(a + rng.uniform(-3.0, 3.0, panda.dof), panda.lower_limits_rad, panda.upper_limits_rad)
        suspects, _, steps = broad.edge_suspects(a, b, 0.01)
        expected = {k for k in range(steps + 1) if broad.state_suspect(a + (b - a) * (k / steps))}
        assert set(suspects.tolist()) == expected and len(suspects) == len(expected)
        flagged += len(expected)
    assert flagged > 0


def test_voxel_clearance_tiers_and_surface_cells(panda: RobotModel) -> None:
    """Tier t keeps clearance * t / tiers from the occupancy; surface cells nested in the voxels
    flag only where the spheres reach a cell, not merely its voxel."""
    home = panda.home_position_rad
    broad = SphereBroadPhase(panda)
    probe = CollisionWorld(panda, padding_m=0.0, broad_phase=False)
    target = panda.frame_pose(home, "panda_grasptarget")[:3, 3]
    for gap in np.arange(0.0, 0.08, 0.002):  # a 2 cm voxel just beyond the fingertips' spheres
        center = (np.floor((target - np.array([0.0, 0.0, 0.02 + gap])) / 0.02) + 0.5) * 0.02
        broad.set_occupied_voxels(center[None], 0.02)
        if not broad.state_suspect(home) and not probe.touches_cubes(home, center[None], 0.02):
            break
    else:
        pytest.fail("no free voxel below the fingertips")
    broad.set_occupied_voxels(center[None], 0.02, 0.06, tiers=3)
    assert broad.clearances_m == pytest.approx((0.0, 0.02, 0.04, 0.06))
    flags = [broad.state_suspect(home, tier=t) for t in range(4)]
    assert flags[0] is False and flags[3] is True and flags == sorted(flags)  # more clearance, more flagged
    assert broad.state_suspect(home) == flags[3]  # the default is the full clearance
    # One surface point in a corner of the voxel: its 5 mm cell flags no tier its voxel does not.
    corner = center + 0.0099
    broad.set_occupied_voxels(center[None], 0.02, 0.06, surface_m=corner[None], surface_cell_m=0.005, tiers=3)
    flags_cells = [broad.state_suspect(home, tier=t) for t in range(4)]
    assert flags_cells == sorted(flags_cells) and sum(flags_cells) <= sum(flags)
    with pytest.raises(ValueError, match="surface_cell_m"):
        broad.set_occupied_voxels(center[None], 0.02, surface_m=corner[None], surface_cell_m=0.003)


def test_fine_surface_cells_flag_fewer_states_than_their_voxels(panda: RobotModel) -> None:
    """One seen point in the far corner of a voxel below the fingertips. Its 5 mm cell is flagged
    only where the spheres (grown by a tier's clearance) reach that cell; the 2 cm voxel alone
    wherever they reach the voxel. So the cell flags a subset of the voxel's (gap, tier) pairs,
    and strictly fewer: the 1.5 cm between the voxel's near face and the cell are not flagged
    for it. (Here the cells' distance field already decides; `test_kernels.py` checks the exact
    cell test behind it.)"""
    home = panda.home_position_rad
    broad = SphereBroadPhase(panda)
    target = panda.frame_pose(home, "panda_grasptarget")[:3, 3]
    by_voxel, by_cell = set(), set()
    for gap in np.arange(0.0, 0.1, 0.004):
        center = (np.floor((target - np.array([0.0, 0.0, 0.02 + gap])) / 0.02) + 0.5) * 0.02
        far_corner = center - 0.0099  # the cell [center - 0.01, center - 0.005] in every axis
        broad.set_occupied_voxels(center[None], 0.02, 0.06, tiers=3)
        by_voxel |= {(round(gap, 3), t) for t in range(4) if broad.state_suspect(home, tier=t)}
        broad.set_occupied_voxels(center[None], 0.02, 0.06, surface_m=far_corner[None], surface_cell_m=0.005, tiers=3)
        by_cell |= {(round(gap, 3), t) for t in range(4) if broad.state_suspect(home, tier=t)}
    assert by_cell <= by_voxel
    assert len(by_cell) < len(by_voxel)
    assert by_cell  # the cell is flagged too, where the spheres reach it


def test_world_spheres_cover_the_padded_hulls_no_looser_than_the_worst_growth(panda: RobotModel) -> None:
    """The world radii are fitted per sphere to the grown hull FCL checks (`grow_hull`); they
    must contain it, and never be looser than adding the hull's worst growth to every sphere."""
    padding = 0.02
    bp = SphereBroadPhase(panda, padding_m=padding, self_pair_tables=False, separating_planes=False)
    model = bp.sphere_model
    shapes = [s for link in panda.collision_link_names for s in panda.link_collision_shapes[link]]
    rng = np.random.default_rng(3)
    tighter = 0
    for s, shape in enumerate(shapes):
        mine = model.shape_index == s
        grown, triangles = grow_hull(shape.hull_vertices, shape.hull_triangles, padding)
        tri = grown[triangles[rng.integers(0, len(triangles), 3000)]]
        samples = np.vstack([np.einsum("nk,nkj->nj", rng.dirichlet(np.ones(3), 3000), tri), grown])
        gap = np.linalg.norm(samples[:, None] - model.centers_link_m[mine][None], axis=2) - bp._radii_world[mine][None]
        assert np.max(np.min(gap, axis=1)) <= 0.0, shape.link
        worst = padded_growth_m(shape.hull_vertices, shape.hull_triangles, padding)
        uniform = model.radii_m[mine] + worst
        assert np.sum(bp._radii_world[mine] ** 3) <= np.sum(uniform ** 3) + 1e-15, shape.link
        assert np.all(bp._radii_world[mine] >= model.radii_m[mine] + padding - 1e-9), shape.link
        tighter += bool(np.any(bp._radii_world[mine] < uniform - 1e-4))
    assert tighter >= len(shapes) // 2  # the fit gains on most links, or it is not worth its cost
