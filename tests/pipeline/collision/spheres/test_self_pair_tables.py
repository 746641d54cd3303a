"""Self-pair gap tables: lower bounds of the true sphere gap; with them (raised by the pieces'
distances, `piece_gaps`) the broad phase flags a subset of what it flags without, and FCL finds
the states only the latter flags free."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robonav.pipeline.collision.spheres.broad_phase import SphereBroadPhase
from robonav.pipeline.collision.spheres.self_pair_tables import SelfPairTables, axis_grids, build_self_pair_tables
from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject


@pytest.fixture(scope="module")
def panda() -> RobotModel:
    """Hand-link6 allowed as in MotionBenchMaker: their spheres touch in every state."""
    return RobotModel.from_config(RobotConfig(
        fixed_joint_positions={"panda_finger_joint1": 0.04, "panda_finger_joint2": 0.04},
        allowed_collision_pairs=(("panda_leftfinger", "panda_rightfinger"), ("panda_hand", "panda_link6"))))


def _table_bound(tables, p: int, q: np.ndarray) -> float:  # noqa: ANN001
    flat = 0
    for d in range(2):
        if tables.slot[p, d] < 0:
            continue
        i = int(np.floor((q[tables.slot[p, d]] - tables.low[p, d]) / tables.step[p, d] + 0.5))
        assert 0 <= i < tables.count[p, d]
        flat = flat * tables.count[p, d] + i
    return float(tables.gap_m[tables.offset[p] + flat])


def _states(robot: RobotModel, count: int, seed: int) -> np.ndarray:
    """Uniform states, half of them with the wrist folded towards the forearm (joints 6 and 7 near
    where the hand meets link 5)."""
    rng = np.random.default_rng(seed)
    qs = rng.uniform(robot.lower_limits_rad, robot.upper_limits_rad, size=(count, robot.dof))
    qs[::2, 5] = rng.uniform(robot.lower_limits_rad[5], robot.lower_limits_rad[5] + 0.4, size=qs[::2].shape[0])
    return qs


def test_tables_bound_the_sphere_gap_from_below(panda: RobotModel) -> None:
    broad = SphereBroadPhase(panda, self_pairs=CollisionWorld(panda).self_collision_pairs)
    # The sphere bounds alone (the broad phase's tables are raised by the pieces' distances too).
    tables = build_self_pair_tables(broad._kin, panda.lower_limits_rad, panda.upper_limits_rad,  # noqa: SLF001
                                    broad._centers_joint, broad._radii_self, broad._link_start,  # noqa: SLF001
                                    broad._self_pairs)  # noqa: SLF001
    links = panda.collision_link_names
    tabled = {(links[a], links[b]) for p, (a, b) in enumerate(broad._self_pairs) if tables.offset[p] >= 0}  # noqa: SLF001
    # The wrist pairs (two joints apart) and the upper arm against the forearm (three: the third
    # swept) have tables; the shoulder against the hand (six) has none.
    assert {("panda_link5", "panda_hand"), ("panda_link5", "panda_link7"), ("panda_link2", "panda_link5")} <= tabled
    assert ("panda_link0", "panda_hand") not in tabled
    model, starts = broad.sphere_model, broad._link_start  # noqa: SLF001
    centers, radii = np.asarray(model.centers_link_m), np.asarray(model.radii_m)
    cleared = margins = 0
    for q in _states(panda, 1500, seed=3):
        poses = panda.link_pose_stack(q)
        world = np.einsum("sij,sj->si", poses[model.link_index, :3, :3], centers) + poses[model.link_index, :3, 3]
        for p, (la, lb) in enumerate(broad._self_pairs):  # noqa: SLF001
            if tables.offset[p] < 0:
                continue
            a, b = slice(starts[la], starts[la + 1]), slice(starts[lb], starts[lb + 1])
            gap = np.min(np.linalg.norm(world[a, None] - world[None, b], axis=2) - radii[a, None] - radii[None, b])
            bound = _table_bound(tables, p, q)
            assert bound <= gap + 1e-12, (links[la], links[lb], q, bound, gap)
            cleared += bound > 0
            margins += 1
    assert cleared > 0.5 * margins  # a useful bound, not only a safe one


def test_with_tables_a_subset_is_flagged_and_the_rest_is_free(panda: RobotModel) -> None:
    pairs = CollisionWorld(panda).self_collision_pairs
    fast, plain = (SphereBroadPhase(panda, padding_m=0.01, self_pairs=pairs, self_pair_tables=t) for t in (True, False))
    exact = CollisionWorld(panda, padding_m=0.01, broad_phase=False)
    scene = [SceneObject("shelf", "box", (0.55, 0.0, 0.4), size_m=(0.3, 0.8, 0.02)),
             SceneObject("post", "cylinder", (0.4, 0.3, 0.3), radius_m=0.05, length_m=0.6)]
    for broad in (fast, plain):
        broad.set_objects(scene)
    exact.set_objects(scene)
    qs = _states(panda, 801, seed=4)
    flagged = only_plain = 0
    for q in qs:
        by_fast, by_plain = fast.state_suspect(q), plain.state_suspect(q)
        assert by_plain or not by_fast
        if by_plain and not by_fast:
            assert not exact.in_collision(q), q
            only_plain += 1
        flagged += by_plain
    assert 0 < flagged < len(qs)
    assert only_plain > 0  # the pieces' distances clear states the spheres and planes do not
    for a, b in zip(qs[:-1:2], qs[1::2]):
        steps_fast, _, n_fast = fast.edge_suspects(a, b, 0.02)
        steps_plain, _, n_plain = plain.edge_suspects(a, b, 0.02)
        assert n_fast == n_plain
        assert set(steps_fast) <= set(steps_plain)


def _hand_made_tables() -> SelfPairTables:
    """Over joint values 0 (a whole turn and more: 2 pi + 1 rad) and 1 (1 rad): pair 0 rigid and
    apart, pair 1 over value 0 and apart, pair 2 over value 1 and apart, pair 3 over both with one
    cell in contact, pair 4 without a table."""
    turn, short = (-math.pi - 0.5, (2 * math.pi + 1) / 3, 4), (0.0, 0.5, 3)
    rows = [((-1, -1), None, None), ((0, -1), turn, None), ((1, -1), short, None), ((0, 1), turn, short)]
    offset, slot = np.full(5, -1), np.full((5, 2), -1)
    low, step, count = np.zeros((5, 2)), np.ones((5, 2)), np.ones((5, 2), dtype=np.int64)
    gaps = []
    for p, (slots, first, second) in enumerate(rows):
        offset[p], slot[p] = sum(len(g) for g in gaps), slots
        for d, grid in enumerate((first, second)):
            if grid is not None:
                low[p, d], step[p, d], count[p, d] = grid
        gap = np.full(int(np.prod(count[p])), 0.01)
        gap[-1] = 0.0 if p == 3 else gap[-1]
        gaps.append(gap)
    return SelfPairTables(offset, slot, low, step, count, np.concatenate(gaps))


def test_tables_over_one_joint_share_its_grid() -> None:
    tables = _hand_made_tables()
    low, step, count, axis = axis_grids(tables, 3)
    assert count.tolist() == [4, 3, 0, 1] and low[1] == 0.0 and step[1] == 0.5
    assert axis.tolist() == [[3, 3], [0, 3], [1, 3], [0, 1], [3, 3]]  # 3: the unused axis
    tables.low[3, 1] = 0.1
    with pytest.raises(ValueError, match="joint value 1"):
        axis_grids(tables, 3)
