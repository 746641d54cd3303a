"""The goal set of a query and the reasons a start or goal is refused, on the Panda beside a block."""

from __future__ import annotations

import numpy as np
import pytest

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.planning.config import PlannerConfig
from robonav.pipeline.planning.goal_set import NEAR_GOALS_KEPT, goal_set, state_problem
from robonav.pipeline.planning.ik import pose_error
from robonav.pipeline.planning.problem import PlanOutcome, PlanProblem, PoseGoal
from robonav.pipeline.planning.result import PlanStatus
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject

BLOCK = SceneObject("block", "box", (0.307, 0.0, 0.44), size_m=(0.08, 0.08, 0.08))
CONFIG = PlannerConfig()


@pytest.fixture(scope="module")
def world(panda: RobotModel) -> CollisionWorld:
    world = CollisionWorld(panda, padding_m=0.01)
    world.set_objects([BLOCK])
    return world


def _free(world: CollisionWorld):  # noqa: ANN202 (a StateValidFn)
    return lambda q: not world.in_collision(q)


def _touching(panda: RobotModel, world: CollisionWorld) -> np.ndarray:
    """The home pose turned about the base until the hand first touches the block."""
    for angle in np.linspace(1.0, 0.0, 101):
        q = panda.home_position_rad.copy()
        q[0] = angle
        if world.in_collision(q):
            return q
    raise AssertionError("the block is out of the hand's way")


def test_state_problem_names_limits_pairs_and_workspace(panda: RobotModel, world: CollisionWorld) -> None:
    free = panda.home_position_rad.copy()
    free[0] = -1.0
    assert state_problem(panda, world, free, _free(world), "start", PlanStatus.START_INVALID) is None
    beyond = free.copy()
    beyond[3] = panda.upper_limits_rad[3] + 0.1
    outcome = state_problem(panda, world, beyond, _free(world), "goal", PlanStatus.GOAL_INVALID)
    assert outcome is not None and outcome.status is PlanStatus.OUT_OF_BOUNDS
    assert outcome.details["which"] == "goal" and len(outcome.details["violations"]) == 1
    touching = _touching(panda, world)
    outcome = state_problem(panda, world, touching, _free(world), "goal", PlanStatus.GOAL_INVALID)
    assert outcome is not None and outcome.status is PlanStatus.GOAL_INVALID
    assert outcome.details["positions"] == touching.tolist()
    assert outcome.details["pairs"] == [f"{a}|{b}" for a, b in world.collisions(touching)]
    assert any(pair.endswith(f"|{BLOCK.name}") for pair in outcome.details["pairs"])
    outcome = state_problem(panda, world, free, lambda _q: False, "start", PlanStatus.START_INVALID)
    assert outcome is not None and outcome.status is PlanStatus.START_INVALID and outcome.details["workspace"]


def test_joint_goals_drop_colliding_members_and_tolerance_replaces_them(panda: RobotModel,
                                                                        world: CollisionWorld) -> None:
    start = panda.home_position_rad.copy()
    start[0] = -1.0
    touching = _touching(panda, world)
    other = start.copy()
    other[0] = -2.0
    rng = np.random.default_rng(0)
    kept = goal_set(panda, world, CONFIG, PlanProblem(start, np.array([touching, other])), start, _free(world), rng)
    np.testing.assert_array_equal(kept, [other])
    refused = goal_set(panda, world, CONFIG, PlanProblem(start, touching), start, _free(world), rng)
    assert isinstance(refused, PlanOutcome) and refused.status is PlanStatus.GOAL_INVALID
    assert refused.details["positions"] == touching.tolist()

    def near(seed: int) -> np.ndarray:
        problem = PlanProblem(start, touching, goal_tolerance_rad=0.05)
        found = goal_set(panda, world, CONFIG, problem, start, _free(world), np.random.default_rng(seed))
        assert isinstance(found, np.ndarray)
        return found

    found = near(1)
    assert 1 <= len(found) <= NEAR_GOALS_KEPT
    offsets = np.max(np.abs(found - touching), axis=1)
    assert np.all(offsets <= 0.05 + 1e-12) and np.all(np.diff(offsets) >= 0)  # nearest first
    assert not any(world.in_collision(q) for q in found)
    np.testing.assert_array_equal(near(1), found)  # the request's seed decides


@pytest.mark.parametrize("problem", [
    PlanProblem(np.zeros(7)),
    PlanProblem(np.zeros(7), np.zeros(7), pose_goal=PoseGoal("panda_hand", np.eye(4))),
    PlanProblem(np.zeros(7), np.zeros((0, 7))),
    PlanProblem(np.zeros(7), np.zeros(6)),
    PlanProblem(np.zeros(7), np.zeros(7), goal_tolerance_rad=float("nan")),
    PlanProblem(np.zeros(7), np.zeros(7), goal_tolerance_rad=-0.1),
], ids=["no goal", "two goals", "empty set", "wrong length", "nan tolerance", "negative tolerance"])
def test_malformed_goals_are_refused_by_name(panda: RobotModel, world: CollisionWorld, problem: PlanProblem) -> None:
    with pytest.raises(ValueError, match="goal"):
        goal_set(panda, world, CONFIG, problem, panda.home_position_rad, _free(world), np.random.default_rng(0))


def test_pose_goal_gives_ik_solutions_within_tolerance_or_says_unreachable(panda: RobotModel,
                                                                           world: CollisionWorld) -> None:
    start = panda.home_position_rad.copy()
    start[0] = -1.0
    q_target = panda.home_position_rad.copy()
    q_target[0] = -0.6
    target = panda.frame_pose(q_target, "panda_hand")
    pose = PoseGoal("panda_hand", target, position_tolerance_m=1e-3, orientation_tolerance_rad=0.01)
    solutions = goal_set(panda, world, CONFIG, PlanProblem(start, pose_goal=pose), start, _free(world),
                         np.random.default_rng(3))
    assert isinstance(solutions, np.ndarray) and 1 <= len(solutions) <= CONFIG.ik_solutions
    for q in solutions:
        position_error_m, orientation_error_rad = pose_error(panda, q, target, "panda_hand")
        assert position_error_m <= 1e-3 and orientation_error_rad <= 0.01
        assert panda.check_joint_limits(q) == [] and not world.in_collision(q)
    far = np.eye(4)
    far[:3, 3] = (3.0, 0.0, 0.5)
    problem = PlanProblem(start, pose_goal=PoseGoal("panda_hand", far, orientation_tolerance_rad=None))
    outcome = goal_set(panda, world, CONFIG, problem, start, _free(world), np.random.default_rng(3))
    assert isinstance(outcome, PlanOutcome) and outcome.status is PlanStatus.GOAL_UNREACHABLE
    assert outcome.details["position_error_m"] > 1.0
