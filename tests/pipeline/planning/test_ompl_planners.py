"""OMPL planners on a 2-D point robot and on the Panda with a real CollisionWorld."""

from __future__ import annotations

import gc
import weakref

import numpy as np
import pytest

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.planning.metrics import path_length_rad
from robonav.pipeline.planning.ompl_planners import PLANNER_CLASSES, JointSpaceProblem, OmplSpace, plan_ompl, seed_ompl_once
from robonav.pipeline.planning.result import PlanStatus
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject

WALL = (0.45, 0.0, 0.55, 0.8)  # x0, y0, x1, y1: a wall with a gap above it
START, GOAL = np.array([0.1, 0.1]), np.array([0.9, 0.1])


@pytest.fixture(autouse=True, scope="module")
def _seed() -> None:
    seed_ompl_once(0)


def _plan(robot, start=START, goal=GOAL, time_limit_s=2.0, planner_id="rrtconnect"):
    return plan_ompl(planner_id, start, goal, lower_rad=robot.lower, upper_rad=robot.upper, is_valid=robot.is_valid,
                            motion_valid=robot.motion_valid, time_limit_s=time_limit_s)


@pytest.mark.parametrize("planner_id", sorted(PLANNER_CLASSES))
def test_path_around_wall(make_point_robot, planner_id: str) -> None:
    robot = make_point_robot([WALL])
    result = _plan(robot, time_limit_s=0.5, planner_id=planner_id)
    assert result.status is PlanStatus.SUCCESS, result.detail
    path = result.path
    assert path.shape[1] == 2 and path.shape[0] >= 3  # the wall forbids the direct segment
    np.testing.assert_array_equal(path[0], START)
    np.testing.assert_array_equal(path[-1], GOAL)
    assert all(robot.motion_valid(a, b) for a, b in zip(path[:-1], path[1:]))
    assert np.all(path >= 0.0) and np.all(path <= 1.0)
    assert np.max(path[:, 1]) > 0.8  # it went over the wall
    assert 0 < result.planning_time_s < 1.5


def test_direct_segment_when_free(make_point_robot) -> None:
    result = _plan(make_point_robot([]))
    assert result.status is PlanStatus.SUCCESS
    np.testing.assert_array_equal(result.path, [START, GOAL])


def test_invalid_start_goal_and_bounds(make_point_robot) -> None:
    robot = make_point_robot([WALL])
    assert _plan(robot, start=np.array([0.5, 0.5])).status is PlanStatus.START_INVALID
    assert _plan(robot, goal=np.array([0.5, 0.5])).status is PlanStatus.GOAL_INVALID
    result = _plan(robot, goal=np.array([0.9, 1.2]))
    assert result.status is PlanStatus.OUT_OF_BOUNDS and result.path is None
    assert "goal" in result.detail and "joint 1" in result.detail and "upper bound 1" in result.detail


def test_enclosed_goal_times_out_within_budget(make_point_robot) -> None:
    box = [(0.7, 0.0, 0.72, 0.3), (0.7, 0.28, 1.0, 0.3)]  # with the square's edges: the goal is enclosed
    robot = make_point_robot(box)
    result = _plan(robot, time_limit_s=0.3)
    assert result.status is PlanStatus.TIMEOUT and result.path is None
    assert 0.3 <= result.planning_time_s < 1.0


def test_bad_input_raises(make_point_robot) -> None:
    robot = make_point_robot([])
    with pytest.raises(ValueError, match=r"q_goal must have shape \(2,\)"):
        _plan(robot, goal=np.zeros(3))
    with pytest.raises(ValueError, match=r"q_start\[1\] must be finite"):
        _plan(robot, start=np.array([0.1, np.nan]))
    with pytest.raises(ValueError, match="unknown planner_id 'nope'"):
        _plan(robot, planner_id="nope")
    with pytest.raises(ValueError, match="time_limit_s"):
        _plan(robot, time_limit_s=0.0)
    with pytest.raises(ValueError, match=r"lower_rad\[0\]"):
        plan_ompl("rrtconnect", START, GOAL, lower_rad=np.ones(2), upper_rad=np.ones(2), is_valid=robot.is_valid,
                         motion_valid=robot.motion_valid, time_limit_s=1.0)


def test_seed_only_once() -> None:
    seed_ompl_once(1)
    assert seed_ompl_once(2) is False
    with pytest.raises(ValueError, match="seed"):
        seed_ompl_once(-1)


def test_panda_around_block(panda: RobotModel) -> None:
    world = CollisionWorld(panda, padding_m=0.01)
    world.set_objects([SceneObject("block", "box", (0.307, 0.0, 0.44), size_m=(0.08, 0.08, 0.08))])
    start, goal = panda.home_position_rad.copy(), panda.home_position_rad.copy()
    start[0], goal[0] = -1.0, 1.0
    resolution_rad = 0.02
    assert not world.motion_valid(start, goal, resolution_rad)
    result = plan_ompl(
        "rrtconnect", start, goal, lower_rad=panda.lower_limits_rad, upper_rad=panda.upper_limits_rad,
        is_valid=lambda q: not world.in_collision(q),
        motion_valid=lambda a, b: world.motion_valid(a, b, resolution_rad),
        time_limit_s=5.0,
    )
    assert result.status is PlanStatus.SUCCESS, result.detail
    np.testing.assert_array_equal(result.path[0], start)
    np.testing.assert_array_equal(result.path[-1], goal)
    assert world.path_valid(result.path, resolution_rad)
    assert all(panda.check_joint_limits(q) == [] for q in result.path)


def _space(robot) -> OmplSpace:
    return OmplSpace(JointSpaceProblem(robot.lower, robot.upper, robot.is_valid, robot.motion_valid))


def test_rrtstar_is_not_longer_than_rrtconnect(make_point_robot) -> None:
    space = _space(make_point_robot([WALL]))
    goals = GOAL[None]
    connect = space.solve("rrtconnect", START, goals, time_limit_s=1.0)
    star = space.solve("rrtstar", START, goals, time_limit_s=1.0)
    assert connect.success and star.success
    assert path_length_rad(star.path) <= path_length_rad(connect.path) + 1e-9


def test_prm_reuses_its_roadmap_until_told_to_forget(make_point_robot) -> None:
    space = _space(make_point_robot([WALL]))
    first = space.solve("prm", START, GOAL[None], time_limit_s=0.3)
    size = space.roadmap_size("prm")
    assert first.success and size > 0
    second = space.solve("prm", np.array([0.1, 0.2]), np.array([[0.9, 0.2]]), time_limit_s=0.3)
    assert second.success
    assert space.roadmap_size("prm") >= size  # grown from the kept roadmap, not rebuilt
    space.forget_planners()
    assert space.roadmap_size("prm") == 0


def test_resume_grows_the_trees_of_the_unsolved_query_on(make_point_robot) -> None:
    closed, opened = make_point_robot([(0.45, 0.0, 0.55, 1.0)]), make_point_robot([WALL])
    world = [closed]  # a stricter check first (the wall without its gap), then the looser one
    start_checks = []

    def is_valid(q: np.ndarray) -> bool:
        start_checks.extend([1] if np.array_equal(q, START) else [])
        return world[0].is_valid(q)

    space = OmplSpace(JointSpaceProblem(closed.lower, closed.upper, is_valid, lambda a, b: world[0].motion_valid(a, b)))
    assert space.solve("rrtconnect", START, GOAL[None], time_limit_s=0.2).status is PlanStatus.TIMEOUT
    assert len(start_checks) == 1  # OMPL checks a start as it roots a tree there
    world[0] = opened
    resumed = space.solve("rrtconnect", START, GOAL[None], time_limit_s=2.0, resume=True)
    assert resumed.success, resumed.detail
    assert len(start_checks) == 1  # grown on from the kept trees: no new root
    assert all(opened.motion_valid(a, b) for a, b in zip(resumed.path[:-1], resumed.path[1:]))
    # Solved, nothing is kept: resuming starts afresh; so does another query or a world change.
    assert space.solve("rrtconnect", START, GOAL[None], time_limit_s=2.0, resume=True).success
    assert len(start_checks) == 2
    world[0] = closed
    space.solve("rrtconnect", START, GOAL[None], time_limit_s=0.1)
    space.forget_planners()
    world[0] = opened
    assert space.solve("rrtconnect", START, GOAL[None], time_limit_s=2.0, resume=True).success
    assert len(start_checks) == 4


def test_the_focus_box_grows_the_ends_by_the_margin_within_the_bounds(make_point_robot) -> None:
    robot = make_point_robot([])
    space = OmplSpace(JointSpaceProblem(robot.lower, robot.upper, robot.is_valid, robot.motion_valid),
                      focus_margin_of_range=0.1)
    lower, upper = space.focus_box(np.array([0.2, 0.05]), np.array([[0.3, 0.5], [0.25, 0.6]]))
    np.testing.assert_allclose(lower, [0.1, 0.0])  # 0.05 - 0.1 is cut at the bound
    np.testing.assert_allclose(upper, [0.4, 0.7])
    assert space.focus_box(np.array([0.05, 0.05]), np.array([[0.95, 0.95]])) is None  # all of it
    unfocused = OmplSpace(JointSpaceProblem(robot.lower, robot.upper, robot.is_valid, robot.motion_valid))
    assert unfocused.focus_box(np.array([0.2, 0.2]), np.array([[0.3, 0.3]])) is None
    with pytest.raises(ValueError, match="focus_margin_of_range"):
        OmplSpace(JointSpaceProblem(robot.lower, robot.upper, robot.is_valid, robot.motion_valid),
                  focus_margin_of_range=float("nan"))


@pytest.mark.parametrize("margin", [0.0, 0.1])
def test_a_focused_search_samples_around_its_ends_first(make_point_robot, margin: float) -> None:
    # A wall between start and goal with a narrow gap level with them: the trees need
    # nothing far away, and unfocused they grow everywhere before they find it.
    robot = make_point_robot([(0.45, 0.0, 0.55, 0.34), (0.45, 0.36, 0.55, 1.0)])
    checked: list[np.ndarray] = []

    def motion_valid(a: np.ndarray, b: np.ndarray) -> bool:
        checked.extend([a, b])
        return robot.motion_valid(a, b)

    farthest = []
    for _ in range(10):  # unfocused, 6 searches in 10 go beyond the box
        checked.clear()
        space = OmplSpace(JointSpaceProblem(robot.lower, robot.upper, robot.is_valid, motion_valid),
                          range_rad=0.05, focus_margin_of_range=margin)
        result = space.solve("rrtconnect", np.array([0.3, 0.35]), np.array([[0.7, 0.35]]), time_limit_s=2.0)
        assert result.success, result.detail
        farthest.append(max(abs(q[1] - 0.35) for q in checked))
    if margin:
        assert max(farthest) <= margin + 1e-9  # inside the box: y within 0.1 of the ends
    else:
        assert max(farthest) > 0.1, farthest


def test_a_focused_search_leaves_the_box_when_the_way_is_outside(make_point_robot) -> None:
    # A wall across the whole focus box: the only way round passes far above it.
    robot = make_point_robot([(0.45, 0.0, 0.55, 0.8)])
    space = OmplSpace(JointSpaceProblem(robot.lower, robot.upper, robot.is_valid, robot.motion_valid),
                      focus_margin_of_range=0.1)
    result = space.solve("rrtconnect", np.array([0.3, 0.3]), np.array([[0.7, 0.3]]), time_limit_s=0.5)
    assert result.success, result.detail
    assert result.path[:, 1].max() > 0.8
    assert all(robot.motion_valid(a, b) for a, b in zip(result.path[:-1], result.path[1:]))


def test_goal_set_ends_at_one_of_the_goals_and_drops_invalid_ones(make_point_robot) -> None:
    robot = make_point_robot([WALL])
    goals = np.array([[0.5, 0.5], [0.9, 0.1], [0.9, 0.9]])  # the first is inside the wall
    result = _plan(robot, goal=goals)
    assert result.success
    assert any(np.array_equal(result.path[-1], g) for g in goals[1:])
    assert _plan(robot, goal=goals[:1]).status is PlanStatus.GOAL_INVALID


class _Owner:
    """Holds its space and gives it validity callbacks that hold the owner, as `MotionPlanner`
    does (its callbacks reach its collision world)."""

    def __init__(self, robot) -> None:
        self.robot = robot
        self.space = OmplSpace(JointSpaceProblem(robot.lower, robot.upper, lambda q: self.robot.is_valid(q),
                                                 lambda a, b: self.robot.motion_valid(a, b)))


@pytest.mark.parametrize("solve", [False, True])
def test_space_and_its_owner_are_collected(make_point_robot, solve: bool) -> None:
    # OMPL holds the callbacks from C++, out of the garbage collector's sight: a callback that
    # held its owner would keep the owner, its world and the space alive for good.
    owner = _Owner(make_point_robot([WALL]))
    if solve:
        result = owner.space.solve("rrtconnect", START, GOAL[None], time_limit_s=0.5)
        assert result.status is PlanStatus.SUCCESS
        assert owner.space.solve("rrtconnect", START, np.array([[0.5, 0.5]]), time_limit_s=0.05).status is PlanStatus.TIMEOUT
    owner_ref, space_ref = weakref.ref(owner), weakref.ref(owner.space)
    del owner
    gc.collect()
    assert owner_ref() is None and space_ref() is None
