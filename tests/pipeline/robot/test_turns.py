"""Continuous joints: a goal's equivalent angle nearest a reference within the range, and joint
distances modulo a turn."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robonav.pipeline.robot.turns import TURN_RAD, joint_distance_rad, nearest_turn_rad

LOWER = np.array([-2.0 * math.pi, 0.0])
UPPER = np.array([2.0 * math.pi, 0.5])
TURNING = np.array([True, False])


@pytest.mark.parametrize(("reference", "goal", "expected"), [
    (3.0, -3.0, -3.0 + TURN_RAD),  # the short way across +-pi
    (-3.0, 3.0, 3.0 - TURN_RAD),
    (0.0, 7.0, 7.0 - TURN_RAD),  # a goal outside the range has an equivalent inside
    (0.0, -4.0, -4.0 + TURN_RAD),
    (6.0, 0.5, 0.5),  # 0.5 + 2 pi lies beyond the upper bound: the nearest inside is the goal itself
    (5.0, 2 * math.pi, 2 * math.pi),  # a goal on a bound keeps its turn
    (1.0, 1.2, 1.2),
])
def test_the_nearest_equivalent_inside_the_range_is_chosen(reference: float, goal: float, expected: float) -> None:
    wrapped = nearest_turn_rad(np.array([goal, 0.3]), np.array([reference, 0.1]), LOWER, UPPER, TURNING)
    assert wrapped[0] == pytest.approx(expected, abs=1e-12)
    assert wrapped[1] == 0.3, "a joint that does not turn is left as given"
    # It is the nearest of every equivalent within the range, found by enumerating them.
    candidates = [goal + k * TURN_RAD for k in range(-4, 5) if LOWER[0] - 1e-12 <= goal + k * TURN_RAD <= UPPER[0] + 1e-12]
    assert abs(wrapped[0] - reference) == pytest.approx(min(abs(c - reference) for c in candidates), abs=1e-12)


def test_goal_sets_wrap_row_by_row_and_narrow_ranges_are_left_to_the_limit_check() -> None:
    goals = np.array([[-3.0, 0.2], [3.5, 0.4]])
    wrapped = nearest_turn_rad(goals, np.array([3.0, 0.0]), LOWER, UPPER, TURNING)
    np.testing.assert_allclose(wrapped, [[-3.0 + TURN_RAD, 0.2], [3.5, 0.4]])
    # A range narrower than a turn with no equivalent of the goal in it: the goal stays as given.
    narrow = nearest_turn_rad(np.array([3.0, 0.0]), np.zeros(2), np.array([-1.0, 0.0]), np.array([1.0, 0.5]), TURNING)
    assert narrow[0] == 3.0
    assert nearest_turn_rad(goals, np.zeros(2), LOWER, UPPER, np.zeros(2, bool)) is not goals
    np.testing.assert_array_equal(nearest_turn_rad(goals, np.zeros(2), LOWER, UPPER, np.zeros(2, bool)), goals)


def test_joint_distance_is_modulo_a_turn_for_turning_joints_only() -> None:
    a, b = np.array([3.0 + TURN_RAD, 0.4]), np.array([-3.0, 0.1])
    np.testing.assert_allclose(joint_distance_rad(a, b, TURNING), [TURN_RAD - 6.0, 0.3], atol=1e-12)
    np.testing.assert_allclose(joint_distance_rad(a, b, np.zeros(2, bool)), [6.0 + TURN_RAD, 0.3], atol=1e-12)
    assert joint_distance_rad(np.array([math.pi, 0.0]), np.array([-math.pi, 0.0]), TURNING)[0] == pytest.approx(0.0, abs=1e-12)
