"""The path re-check and the segments it trusts."""

from __future__ import annotations

import numpy as np

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.planning.recheck import path_rechecked, recording, segment_key
from robonav.pipeline.robot.model import RobotModel


def test_recording_notes_only_accepted_segments_by_direction() -> None:
    a, b, c = np.zeros(2), np.ones(2), np.full(2, 2.0)
    checked: set[bytes] = set()
    check = recording(lambda p, q: q[0] < 1.5, checked)
    assert check(a, b) and not check(a, c)
    assert checked == {segment_key(a, b)} and segment_key(b, a) not in checked


def test_recheck_skips_what_was_accepted_and_asks_the_rest(panda: RobotModel) -> None:
    world = CollisionWorld(panda, padding_m=0.0)
    home = panda.home_position_rad
    path = np.array([home, home + 0.2, home + 0.4])
    asked: list[int] = []

    def count(a: np.ndarray, b: np.ndarray) -> bool:
        asked.append(1)
        return True

    checked = {segment_key(path[0], path[1])}
    # At the edge resolution the accepted segment is not asked again, the other one is.
    assert path_rechecked(world, path, count, checked, path_check_rad=0.0, edge_rad=0.02, own_check=True)
    assert len(asked) == 1
    # A finer check goes to the world; the request's own bounds are asked of the unknown segment only.
    asked.clear()
    assert path_rechecked(world, path, count, checked, path_check_rad=0.01, edge_rad=0.02, own_check=False)
    assert len(asked) == 1
    assert not path_rechecked(world, path, lambda a, b: False, set(), path_check_rad=0.0, edge_rad=0.02,
                              own_check=True)
