"""solve_ik on pybullet_data's Panda: reachability, tolerances, limits, goal sets, validity, bad input."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from robonav.pipeline.planning.ik import IkStatus, pose_error, solve_ik
from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.transforms import PoseSpec

LINK = "panda_hand"


def _random_q(robot: RobotModel, rng: np.random.Generator) -> np.ndarray:
    return rng.uniform(robot.lower_limits_rad, robot.upper_limits_rad)


def _rotation_about(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle_rad) * k + (1 - math.cos(angle_rad)) * k @ k


def _within_limits(robot: RobotModel, solutions: np.ndarray) -> bool:
    return all(robot.check_joint_limits(q) == [] for q in solutions)


@pytest.mark.parametrize("case", range(6))
def test_reaches_fk_target_from_random_seed(panda: RobotModel, case: int) -> None:
    rng = np.random.default_rng(100 + case)
    q_true = _random_q(panda, rng)
    target = panda.frame_pose(q_true, LINK)
    result = solve_ik(panda, target, LINK, rng=rng, seed_q=_random_q(panda, rng),
                      position_tolerance_m=1e-3, orientation_tolerance_rad=0.01)
    assert result.status is IkStatus.SUCCESS, result.detail
    assert result.solutions.shape == (1, panda.dof)
    position, angle = pose_error(panda, result.solutions[0], target, LINK)
    assert position <= 1e-3 and angle <= 0.01
    assert _within_limits(panda, result.solutions)
    assert result.iterations >= 1 and result.solve_time_s < 1.0


def test_seed_at_a_solution_is_kept(panda: RobotModel) -> None:
    rng = np.random.default_rng(7)
    q_true = _random_q(panda, rng)
    result = solve_ik(panda, panda.frame_pose(q_true, LINK), LINK, rng=rng, seed_q=q_true)
    assert result.status is IkStatus.SUCCESS and result.attempts == 1
    np.testing.assert_allclose(result.solutions[0], q_true, atol=1e-12)


def test_unreachable_target_fails_fast(panda: RobotModel) -> None:
    target = np.eye(4)
    target[:3, 3] = (3.0, 0.0, 0.5)
    result = solve_ik(panda, target, LINK, rng=np.random.default_rng(0), max_restarts=10)
    assert result.status is IkStatus.UNREACHABLE, result.detail
    assert result.solutions.shape == (0, panda.dof) and result.attempts == 11
    assert result.best_position_error_m > 1.5  # the Panda reaches about 0.9 m
    assert result.solve_time_s < 0.5


def test_orientation_tolerance_is_respected(panda: RobotModel) -> None:
    rng = np.random.default_rng(3)
    q_true = _random_q(panda, rng)
    reached = panda.frame_pose(q_true, LINK)
    for tolerance in (0.3, 0.05, 0.005):
        result = solve_ik(panda, reached, LINK, rng=rng, orientation_tolerance_rad=tolerance,
                          position_tolerance_m=5e-4, max_solutions=3, max_restarts=30)
        assert result.status is IkStatus.SUCCESS, (tolerance, result.detail)
        for q in result.solutions:
            position, angle = pose_error(panda, q, reached, LINK)
            assert position <= 5e-4 and angle <= tolerance


def test_position_only_goal_ignores_orientation(panda: RobotModel) -> None:
    rng = np.random.default_rng(11)
    target = panda.frame_pose(_random_q(panda, rng), LINK)
    # A reachable position with an orientation chosen at random: position-only IK needs only the former.
    target[:3, :3] = _rotation_about(rng.normal(size=3), 2.0) @ target[:3, :3]
    for tolerance in (None, math.inf):
        result = solve_ik(panda, target, LINK, rng=np.random.default_rng(0), orientation_tolerance_rad=tolerance)
        assert result.status is IkStatus.SUCCESS, result.detail
        position, _ = pose_error(panda, result.solutions[0], target, LINK)
        assert position <= 1e-3
        assert result.best_orientation_error_rad == 0.0


def test_goal_set_is_distinct_sorted_and_within_limits(panda: RobotModel) -> None:
    rng = np.random.default_rng(5)
    q_true = _random_q(panda, rng)
    target = panda.frame_pose(q_true, LINK)
    seed = _random_q(panda, rng)
    result = solve_ik(panda, target, LINK, rng=rng, seed_q=seed, max_solutions=5, max_restarts=40)
    assert result.status is IkStatus.SUCCESS
    solutions = result.solutions
    assert 2 <= solutions.shape[0] <= 5  # a 7-DoF arm has a continuum of solutions
    for i in range(len(solutions)):
        for j in range(i):
            assert np.max(np.abs(solutions[i] - solutions[j])) > 1e-3
    distances = np.linalg.norm(solutions - seed, axis=1)
    assert np.all(np.diff(distances) >= 0)
    assert _within_limits(panda, solutions)
    for q in solutions:
        position, angle = pose_error(panda, q, target, LINK)
        assert position <= 1e-3 and angle <= 0.01


def test_validity_filter(panda: RobotModel) -> None:
    rng = np.random.default_rng(9)
    q_true = _random_q(panda, rng)
    target = panda.frame_pose(q_true, LINK)

    result = solve_ik(panda, target, LINK, rng=np.random.default_rng(1), is_valid=lambda q: False, max_restarts=5)
    assert result.status is IkStatus.GOAL_IN_COLLISION, result.detail
    assert result.solutions.shape == (0, panda.dof) and result.rejected_invalid >= 1
    assert str(result.rejected_invalid) in result.detail

    # A filter that accepts only one half of the joint-1 range: every solution returned obeys it.
    side = 1.0 if q_true[0] >= 0 else -1.0
    seen: list[np.ndarray] = []

    def is_valid(q: np.ndarray) -> bool:
        seen.append(q)
        return bool(side * q[0] >= 0)

    result = solve_ik(panda, target, LINK, rng=np.random.default_rng(2), is_valid=is_valid, max_solutions=3,
                      max_restarts=40)
    assert result.status is IkStatus.SUCCESS
    assert all(side * q[0] >= 0 for q in result.solutions)
    assert len(seen) == result.solutions.shape[0] + result.rejected_invalid


def test_joint_order_differing_from_pinocchio_order() -> None:
    base = RobotConfig()
    reversed_config = RobotConfig(
        joint_names=tuple(reversed(base.joint_names)),
        max_velocity_rad_s=tuple(reversed(base.max_velocity_rad_s)),
        max_acceleration_rad_s2=tuple(reversed(base.max_acceleration_rad_s2)),
        max_jerk_rad_s3=tuple(reversed(base.max_jerk_rad_s3)),
        home_position_rad=tuple(reversed(base.home_position_rad)),
        fixed_joint_positions={"panda_finger_joint1": 0.04, "panda_finger_joint2": 0.04},
    )
    robot = RobotModel.from_config(reversed_config)
    assert list(robot._q_index) != list(range(robot.dof))
    rng = np.random.default_rng(4)
    q_true = _random_q(robot, rng)
    target = robot.frame_pose(q_true, LINK)
    result = solve_ik(robot, target, LINK, rng=rng, seed_q=_random_q(robot, rng))
    assert result.status is IkStatus.SUCCESS, result.detail
    position, angle = pose_error(robot, result.solutions[0], target, LINK)
    assert position <= 1e-3 and angle <= 0.01
    assert _within_limits(robot, result.solutions)


def test_same_seed_same_answer(panda: RobotModel) -> None:
    target = panda.frame_pose(_random_q(panda, np.random.default_rng(6)), LINK)
    a = solve_ik(panda, target, LINK, rng=np.random.default_rng(42), max_solutions=3, max_restarts=20)
    b = solve_ik(panda, target, LINK, rng=np.random.default_rng(42), max_solutions=3, max_restarts=20)
    np.testing.assert_array_equal(a.solutions, b.solutions)


def test_bad_input_raises(panda: RobotModel) -> None:
    rng = np.random.default_rng(0)
    good = panda.frame_pose(panda.home_position_rad, LINK)
    with pytest.raises(ValueError, match=r"shape \(4, 4\)"):
        solve_ik(panda, good[:3], LINK, rng=rng)
    nan = good.copy()
    nan[0, 3] = np.nan
    with pytest.raises(ValueError, match="finite"):
        solve_ik(panda, nan, LINK, rng=rng)
    skewed = good.copy()
    skewed[:3, :3] *= 2.0
    with pytest.raises(ValueError, match="orthonormal"):
        solve_ik(panda, skewed, LINK, rng=rng)
    with pytest.raises(ValueError, match="not a frame"):
        solve_ik(panda, good, "no_such_link", rng=rng)
    with pytest.raises(ValueError, match="position_tolerance_m"):
        solve_ik(panda, good, LINK, rng=rng, position_tolerance_m=0.0)
    with pytest.raises(ValueError, match="orientation_tolerance_rad"):
        solve_ik(panda, good, LINK, rng=rng, orientation_tolerance_rad=-0.1)
    with pytest.raises(ValueError, match="orientation_tolerance_rad"):
        solve_ik(panda, good, LINK, rng=rng, orientation_tolerance_rad=math.nan)
    with pytest.raises(ValueError, match=r"seed_q must have shape \(7,\)"):
        solve_ik(panda, good, LINK, rng=rng, seed_q=np.zeros(3))
    with pytest.raises(ValueError, match=r"seed_q\[2\]"):
        solve_ik(panda, good, LINK, rng=rng, seed_q=np.array([0, 0, np.inf, 0, 0, 0, 0.0]))
    with pytest.raises(ValueError, match="max_iterations"):
        solve_ik(panda, good, LINK, rng=rng, max_iterations=0)
    with pytest.raises(ValueError, match="max_solutions"):
        solve_ik(panda, good, LINK, rng=rng, max_solutions=0)


def test_targets_are_in_the_world_when_the_robot_stands_elsewhere(panda: RobotModel) -> None:
    # A target the robot at the origin reaches is, for the robot moved and turned, the same
    # target moved and turned with it; the solution is the same joint state.
    posed = RobotModel.from_config(dataclasses.replace(
        panda.config, world_from_base=PoseSpec((0.6, -0.4, 0.2), (0.0, 0.0, math.sin(0.6), math.cos(0.6)))))
    rng = np.random.default_rng(31)
    q_true = _random_q(panda, rng)
    target = posed.config.world_from_base.matrix @ panda.frame_pose(q_true, LINK)
    result = solve_ik(posed, target, LINK, rng=rng, seed_q=q_true, position_tolerance_m=1e-4,
                      orientation_tolerance_rad=1e-3)
    assert result.status is IkStatus.SUCCESS and result.attempts == 1, result.detail
    np.testing.assert_allclose(result.solutions[0], q_true, atol=1e-9)
    # The robot at the origin does not reach the moved target from there.
    unmoved = solve_ik(panda, target, LINK, rng=rng, seed_q=q_true, max_restarts=0)
    assert unmoved.status is not IkStatus.SUCCESS
