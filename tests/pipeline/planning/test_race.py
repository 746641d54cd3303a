"""`race`: several OMPL planners on one query in forked processes, on a 2-D point robot."""

from __future__ import annotations

import numpy as np
import pytest

from robonav.pipeline.planning.ompl_planners import JointSpaceProblem, OmplSpace, seed_ompl_once
from robonav.pipeline.planning.race import race
from robonav.pipeline.planning.result import PlanStatus

WALL = (0.45, 0.0, 0.55, 0.8)  # x0, y0, x1, y1: a wall with a gap above it
START, GOAL = np.array([0.1, 0.1]), np.array([0.9, 0.1])


@pytest.fixture(autouse=True, scope="module")
def _seed() -> None:
    seed_ompl_once(0)


def _space(robot) -> OmplSpace:  # noqa: ANN001 (a PointRobot2D)
    return OmplSpace(JointSpaceProblem(robot.lower, robot.upper, robot.is_valid, robot.motion_valid))


def test_race_returns_a_winner_and_stops_the_others(make_point_robot) -> None:
    space = _space(make_point_robot([WALL]))
    winner, result = race(space, ["rrtconnect", "prmstar"], START, GOAL[None], time_limit_s=5.0)
    assert result.success and winner in ("rrtconnect", "prmstar")
    # PRM* alone would use the whole 5 s; the win stopped it long before.
    assert result.planning_time_s < 2.0


def test_race_without_a_solution_says_so_within_its_budget(make_point_robot) -> None:
    # With the square's edges, these walls enclose the goal: no planner can reach it.
    space = _space(make_point_robot([(0.7, 0.0, 0.72, 0.3), (0.7, 0.28, 1.0, 0.3)]))
    winner, result = race(space, ["rrtconnect", "rrt"], START, GOAL[None], time_limit_s=0.3)
    assert winner == "rrtconnect" and not result.success and result.path is None
    assert result.status is PlanStatus.TIMEOUT and "rrtconnect" in result.detail and "rrt:" in result.detail
    assert result.planning_time_s < 5.0


def test_race_needs_a_planner(make_point_robot) -> None:
    with pytest.raises(ValueError, match="at least one"):
        race(_space(make_point_robot([WALL])), [], START, GOAL[None], time_limit_s=0.1)
