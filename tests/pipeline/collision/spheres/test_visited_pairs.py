"""Which self pairs the lane check visits: none a table proves apart at every state, the rest in
groups one bounding-sphere test may skip, and the same answers as every pair on its own."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robonav.pipeline.collision.spheres.broad_phase import SphereBroadPhase
from robonav.pipeline.collision.spheres.visited_pairs import pair_groups, pairs_apart_everywhere
from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.robot.model import RobotModel

from .test_self_pair_tables import _hand_made_tables, _states


def test_apart_everywhere_needs_every_cell_clear_over_whole_turns() -> None:
    tables = _hand_made_tables()
    lower, upper = np.array([-math.pi - 0.5, 0.0, 0.0]), np.array([math.pi + 0.5, 1.0, 1.0])
    # The 1 rad joint's table says nothing of an angle beyond its limits: not apart everywhere.
    assert pairs_apart_everywhere(tables, lower, upper, 1e-9).tolist() == [True, True, False, False, False]


def test_pair_groups_share_the_first_link_and_the_joint_of_the_second() -> None:
    pairs = np.array([(0, 2), (1, 2), (0, 4), (0, 3), (0, 5)])
    link_joint = np.array([0, 1, 2, 2, 3, 3])
    centers = np.array([[0.0, 0, 0], [0, 0, 0], [0.1, 0, 0], [-0.1, 0, 0], [0, 0, 0], [0, 0.3, 0]])
    order, end, center, radius = pair_groups(pairs, np.array([0, 1, 2, 3, 4]), link_joint, centers,
                                             np.array([0.1, 0.1, 0.05, 0.02, 0.1, 0.1]))
    # (0, 2) and (0, 3): link 0 against links 2 and 3, both on joint 2; then link 0 against
    # joint 3's links 4 and 5; link 1's pair alone.
    assert [tuple(pairs[p]) for p in order] == [(0, 2), (0, 3), (0, 4), (0, 5), (1, 2)]
    assert end[[0, 2, 4]].tolist() == [2, 4, 5] and radius[4] == -1.0
    np.testing.assert_allclose(center[0], [0.0, 0.0, 0.0])
    assert radius[0] == pytest.approx(0.15)  # link 2's sphere: 0.1 from the middle, radius 0.05
    np.testing.assert_allclose(center[2], [0.0, 0.15, 0.0])
    assert radius[2] == pytest.approx(0.25)


def test_pairs_apart_at_every_state_are_not_visited(panda: RobotModel) -> None:
    # The fingers are fixed: they and link 7 keep one pose to each other, well apart.
    pairs = CollisionWorld(panda).self_collision_pairs
    broad, every = (SphereBroadPhase(panda, padding_m=0.01, self_pairs=pairs) for _ in range(2))
    links = panda.collision_link_names
    skipped = {(links[a], links[b]) for p, (a, b) in enumerate(broad._self_pairs)  # noqa: SLF001
               if p not in broad._pair_groups[0]}  # noqa: SLF001
    assert skipped == {("panda_link7", "panda_leftfinger"), ("panda_link7", "panda_rightfinger"),
                       ("panda_leftfinger", "panda_rightfinger")}
    # Every pair, each on its own (no group's bounding sphere skips it).
    every._pair_groups = (np.arange(len(pairs)), np.arange(1, len(pairs) + 1), np.zeros((len(pairs), 3)),  # noqa: SLF001
                          np.full(len(pairs), -1.0))
    every._refresh_args()  # noqa: SLF001
    assert (broad._pair_groups[3] >= 0).any()  # noqa: SLF001 (groups: link 7, the hand and the fingers on one joint)
    qs = _states(panda, 400, seed=5)
    assert any(every.self_suspect(q) for q in qs)
    for q in qs:
        assert broad.state_suspect(q) == every.state_suspect(q)
    for a, b in zip(qs[:-1:2], qs[1::2]):
        assert np.array_equal(broad.edge_suspects(a, b, 0.02)[0], every.edge_suspects(a, b, 0.02)[0])
