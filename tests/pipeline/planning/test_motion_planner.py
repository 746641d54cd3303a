"""MotionPlanner on the Panda: goal forms, planners, request parameters, and the statuses they produce."""

from __future__ import annotations

import dataclasses
import gc

import numpy as np
import octomap
import pytest

from robonav.pipeline.collision.spheres.broad_phase import SphereBroadPhase
from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.planning.config import PlannerConfig
from robonav.pipeline.planning.ik import pose_error
from robonav.pipeline.planning.motion_planner import PLANNERS, MotionPlanner, PlanProblem, PoseGoal
from robonav.pipeline.planning.ompl_planners import OmplSpace, seed_ompl_once
from robonav.pipeline.planning.result import PlanStatus
from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject

RESOLUTION_RAD = 0.02
BLOCK = SceneObject("block", "box", (0.307, 0.0, 0.44), size_m=(0.08, 0.08, 0.08))


@pytest.fixture(scope="module")
def setup(panda: RobotModel) -> tuple[MotionPlanner, np.ndarray, np.ndarray]:
    seed_ompl_once(0)
    world = CollisionWorld(panda, padding_m=0.01)
    world.set_objects([BLOCK])
    planner = MotionPlanner(panda, world, PlannerConfig(edge_resolution_rad=RESOLUTION_RAD, range_rad=1.0))
    start, goal = panda.home_position_rad.copy(), panda.home_position_rad.copy()
    start[0], goal[0] = -1.0, 1.0
    assert not world.motion_valid(start, goal, RESOLUTION_RAD)  # the block is in the way
    return planner, start, goal


def _assert_valid_path(planner: MotionPlanner, path: np.ndarray, start: np.ndarray) -> None:
    np.testing.assert_array_equal(path[0], start)
    assert planner.world.path_valid(path, RESOLUTION_RAD)
    assert all(planner.robot.check_joint_limits(q) == [] for q in path)


@pytest.mark.parametrize("planner_id", ["rrtconnect", "rrt", "prm", "bitstar", "auto"])
def test_every_planner_finds_a_valid_path(setup, planner_id: str) -> None:
    planner, start, goal = setup
    time_s = 0.5 if planner_id == "bitstar" else 5.0
    outcome = planner.plan(PlanProblem(start, goal, planner_id=planner_id, allowed_planning_time_s=time_s, seed=1))
    assert outcome.status is PlanStatus.SUCCESS, outcome.detail
    _assert_valid_path(planner, outcome.path, start)
    np.testing.assert_array_equal(outcome.path[-1], goal)
    assert outcome.planner_id in PLANNERS
    assert outcome.path_length_rad > 2.0 and outcome.max_joint_step_rad > 0 and outcome.min_clearance_m > 0


@pytest.mark.parametrize("share, search", [(1.0, "sphere_first"), (0.0, "exact")])
def test_sphere_first_and_exact_searches_both_give_valid_paths(setup, share: float, search: str) -> None:
    _, start, goal = setup
    # Finger pairs allowed, as in the shipped config (open fingers' spheres always touch).
    robot = RobotModel.from_config(RobotConfig(
        fixed_joint_positions={"panda_finger_joint1": 0.04, "panda_finger_joint2": 0.04},
        allowed_collision_pairs=(("panda_leftfinger", "panda_rightfinger"), ("panda_hand", "panda_link6"))))
    world = CollisionWorld(robot, padding_m=0.01)
    world.set_objects([BLOCK])
    planner = MotionPlanner(robot, world, PlannerConfig(edge_resolution_rad=RESOLUTION_RAD, range_rad=1.0,
                                                        sphere_first_share=share))
    outcome = planner.plan(PlanProblem(start, goal, allowed_planning_time_s=5.0, seed=4))
    assert outcome.status is PlanStatus.SUCCESS, outcome.detail
    assert outcome.search == search
    _assert_valid_path(planner, outcome.path, start)
    np.testing.assert_array_equal(outcome.path[-1], goal)


def test_fcl_decides_only_near_anchors_the_spheres_flag(setup, panda: RobotModel) -> None:
    _, start, goal = setup
    world = CollisionWorld(panda, padding_m=0.01)
    world.set_objects([BLOCK])
    planner = MotionPlanner(panda, world, PlannerConfig(edge_resolution_rad=RESOLUTION_RAD, range_rad=1.0,
                                                        sphere_first_share=1.0))
    # A goal beside the block whose spheres touch it while its hulls keep off: FCL must decide there.
    rng = np.random.default_rng(2)
    tight = next(q for q in goal + rng.uniform(-0.4, 0.4, size=(4000, panda.dof)) * (1.5, 1, 1, 1, 1, 1, 1)
                 if not panda.check_joint_limits(q) and world._broad_phase.state_suspect(q)  # noqa: SLF001
                 and not world.in_collision(q))
    # And one as close to the block whose spheres clear it.
    close = next(q for q in tight + rng.uniform(-0.15, 0.15, size=(4000, panda.dof))
                 if not panda.check_joint_limits(q) and not world._broad_phase.state_suspect(q))  # noqa: SLF001
    for target, exact_near in ((close, False), (tight, True)):
        outcome = planner.plan(PlanProblem(start, target, allowed_planning_time_s=5.0, seed=3))
        assert outcome.status is PlanStatus.SUCCESS and outcome.search == "sphere_first", outcome.detail
        _assert_valid_path(planner, outcome.path, start)
        # Where FCL decided what the spheres flag: beside the tight goal, not beside the clear one.
        assert planner._near_anchor(target) is exact_near  # noqa: SLF001
        assert not planner._near_anchor(start)  # noqa: SLF001


def test_sphere_first_is_skipped_against_an_occupancy_map(setup) -> None:
    _, start, goal = setup
    robot = RobotModel.from_config(RobotConfig(
        fixed_joint_positions={"panda_finger_joint1": 0.04, "panda_finger_joint2": 0.04},
        allowed_collision_pairs=(("panda_leftfinger", "panda_rightfinger"), ("panda_hand", "panda_link6"))))
    world = CollisionWorld(robot, padding_m=0.01)
    tree = octomap.OcTree(0.02)
    axis = np.arange(-0.04, 0.041, 0.01)
    cube = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3) + BLOCK.position_m
    tree.insertPointCloud(cube, np.array([0.0, 0.0, 2.0]))
    world.set_octree(tree.writeBinary(), 0.02)
    planner = MotionPlanner(robot, world, PlannerConfig(edge_resolution_rad=RESOLUTION_RAD, range_rad=1.0,
                                                        sphere_first_share=1.0))
    outcome = planner.plan(PlanProblem(start, goal, allowed_planning_time_s=5.0, seed=4))
    assert outcome.status is PlanStatus.SUCCESS and outcome.search == "exact"
    _assert_valid_path(planner, outcome.path, start)


def test_sphere_first_is_skipped_when_self_collision_spheres_always_touch(setup) -> None:
    planner, start, goal = setup  # every finger pair checked: their spheres touch in every state...
    assert planner.world.sphere_self_overflag() < 0.5, "... where the pieces' gap tables and planes clear them"
    # Without either (a fresh robot: the overflag is measured once per robot) every state is suspect.
    robot = RobotModel.from_config(planner.robot.config)
    world = CollisionWorld(robot, padding_m=0.01)
    world.set_objects([BLOCK])
    world._broad_phase = SphereBroadPhase(robot, padding_m=0.01, self_pairs=world.self_collision_pairs,
                                          self_pair_tables=False, separating_planes=False)
    world._broad_phase.set_objects([BLOCK])
    assert world.sphere_self_overflag() > 0.9
    own = MotionPlanner(robot, world, dataclasses.replace(planner.config, sphere_first_share=1.0))
    outcome = own.plan(PlanProblem(start, goal, allowed_planning_time_s=5.0, seed=4))
    assert outcome.status is PlanStatus.SUCCESS and outcome.search == "exact"


def test_goal_set_ends_at_a_member(setup) -> None:
    planner, start, goal = setup
    other = goal.copy()
    other[0] = -2.0  # reachable by turning away from the block
    outcome = planner.plan(PlanProblem(start, np.array([goal, other]), seed=2))
    assert outcome.status is PlanStatus.SUCCESS
    assert outcome.goal_index in (0, 1)
    np.testing.assert_array_equal(outcome.path[-1], [goal, other][outcome.goal_index])


def test_pose_goal_reaches_the_pose_within_tolerance(setup) -> None:
    planner, start, _ = setup
    q_target = planner.robot.home_position_rad.copy()
    q_target[0] = -0.6
    target = planner.robot.frame_pose(q_target, "panda_hand")
    pose = PoseGoal("panda_hand", target, position_tolerance_m=1e-3, orientation_tolerance_rad=0.01)
    outcome = planner.plan(PlanProblem(start, pose_goal=pose, seed=3))
    assert outcome.status is PlanStatus.SUCCESS, outcome.detail
    position_error_m, orientation_error_rad = pose_error(planner.robot, outcome.path[-1], target, "panda_hand")
    assert position_error_m <= 1e-3 and orientation_error_rad <= 0.01
    _assert_valid_path(planner, outcome.path, start)


def test_unreachable_pose_and_pose_inside_the_block(setup) -> None:
    planner, start, _ = setup
    far = np.eye(4)
    far[:3, 3] = (3.0, 0.0, 0.5)
    outcome = planner.plan(PlanProblem(start, pose_goal=PoseGoal("panda_hand", far, orientation_tolerance_rad=None)))
    assert outcome.status is PlanStatus.GOAL_UNREACHABLE
    inside = np.eye(4)
    inside[:3, 3] = BLOCK.position_m
    outcome = planner.plan(PlanProblem(start, pose_goal=PoseGoal("panda_link7", inside, orientation_tolerance_rad=None)))
    assert outcome.status is PlanStatus.GOAL_INVALID, outcome.detail
    # Where the nearest rejected solution collides, for a viewer to show.
    q = np.array(outcome.details["positions"])
    assert outcome.details["which"] == "goal" and outcome.details["rejected"] >= 1
    assert outcome.details["pairs"] == [f"{a}|{b}" for a, b in planner.world.collisions(q)]
    assert any(pair.endswith(f"|{BLOCK.name}") for pair in outcome.details["pairs"]), outcome.details


def test_goal_tolerance_replaces_a_goal_in_collision(setup) -> None:
    planner, start, goal = setup
    # Nudge the goal until the hand just touches the block; a small tolerance finds free states.
    touching = None
    for dq in np.linspace(0, 1.0, 101):
        q = goal.copy()
        q[0] = 1.0 - dq
        if planner.world.in_collision(q):
            touching = q
            break
    assert touching is not None
    refused = planner.plan(PlanProblem(start, touching))
    assert refused.status is PlanStatus.GOAL_INVALID
    assert refused.details["which"] == "goal" and refused.details["positions"] == touching.tolist()
    assert any(pair.endswith(f"|{BLOCK.name}") for pair in refused.details["pairs"]), refused.details
    outcome = planner.plan(PlanProblem(start, touching, goal_tolerance_rad=0.05, seed=4))
    assert outcome.status is PlanStatus.SUCCESS, outcome.detail
    assert np.max(np.abs(outcome.path[-1] - touching)) <= 0.05 + 1e-12


def test_workspace_bounds_are_respected(setup) -> None:
    planner, start, goal = setup
    hand = [planner.robot.frame_pose(q, "panda_hand")[:3, 3] for q in (start, goal)]
    low = np.minimum(*hand) - np.array([0.6, 0.6, 0.3])
    high = np.maximum(*hand) + np.array([0.6, 0.6, 0.3])
    outcome = planner.plan(PlanProblem(start, goal, workspace_min_m=low, workspace_max_m=high, seed=5))
    assert outcome.status is PlanStatus.SUCCESS, outcome.detail
    from robonav.pipeline.planning.metrics import interpolate_path

    for q in interpolate_path(outcome.path, RESOLUTION_RAD):
        p = planner.robot.frame_pose(q, "panda_hand")[:3, 3]
        assert np.all(p >= low - 1e-9) and np.all(p <= high + 1e-9)
    tight = planner.plan(PlanProblem(start, goal, workspace_min_m=hand[0] - 0.01, workspace_max_m=hand[0] + 0.01))
    assert tight.status is PlanStatus.GOAL_INVALID


def test_requests_with_workspace_bounds_leave_no_search_space_behind(setup) -> None:
    # Such a request gets a search space of its own; OMPL holds its callbacks from C++, so one
    # that held its space would keep it (and its trees) in a long-running planner for good.
    planner, start, goal = setup
    hand = [planner.robot.frame_pose(q, "panda_hand")[:3, 3] for q in (start, goal)]
    low, high = np.minimum(*hand) - 0.6, np.maximum(*hand) + 0.6

    def spaces() -> int:
        gc.collect()
        return sum(isinstance(o, OmplSpace) for o in gc.get_objects())

    before = spaces()
    for seed in range(3):
        outcome = planner.plan(PlanProblem(start, goal, workspace_min_m=low, workspace_max_m=high, seed=seed))
        assert outcome.status is PlanStatus.SUCCESS, outcome.detail
    assert spaces() == before


def test_several_attempts_return_the_shortest(setup) -> None:
    planner, start, goal = setup
    outcome = planner.plan(PlanProblem(start, goal, seed=6, simplify=False, num_planning_attempts=4,
                                       allowed_planning_time_s=20.0))
    assert outcome.status is PlanStatus.SUCCESS
    lengths = outcome.attempt_lengths_rad
    assert len(lengths) == 4
    assert outcome.path_length_rad == min(lengths)


def test_prm_roadmap_is_reused_until_the_world_changes(setup) -> None:
    planner, start, goal = setup
    outcome = planner.plan(PlanProblem(start, goal, planner_id="prm", allowed_planning_time_s=2.0))
    assert outcome.status is PlanStatus.SUCCESS, outcome.detail
    first = planner.roadmap_size("prm")
    assert first > 0
    back = planner.plan(PlanProblem(goal, start, planner_id="prm", allowed_planning_time_s=2.0))
    assert back.status is PlanStatus.SUCCESS
    assert planner.roadmap_size("prm") >= first
    planner.world.set_objects([BLOCK])  # same objects, but a new revision: the roadmap is dropped
    assert planner.roadmap_size("prm") == 0


def test_bad_requests_raise(setup) -> None:
    planner, start, goal = setup
    with pytest.raises(ValueError, match="unknown planner_id"):
        planner.plan(PlanProblem(start, goal, planner_id="rrt-connect"))
    with pytest.raises(ValueError, match="exactly one of goals_rad and pose_goal"):
        planner.plan(PlanProblem(start))
    with pytest.raises(ValueError, match="num_planning_attempts"):
        planner.plan(PlanProblem(start, goal, num_planning_attempts=0))
    with pytest.raises(ValueError, match="workspace_min_m"):
        planner.plan(PlanProblem(start, goal, workspace_min_m=np.ones(3), workspace_max_m=np.zeros(3)))
    with pytest.raises(ValueError, match="goal_tolerance_rad"):
        planner.plan(PlanProblem(start, goal, goal_tolerance_rad=float("nan")))


@pytest.mark.parametrize("path_check_rad", [0.0, 0.01])
def test_the_returned_path_is_rechecked_at_the_path_check_resolution(panda: RobotModel, path_check_rad: float) -> None:
    """Edges checked 2 rad apart step over a 2 mm plate in the hand's way; the re-check at
    0.01 rad does not: the straight segment through the plate is never returned, and the
    search draws paths until one passes."""
    start, goal = panda.home_position_rad.copy(), panda.home_position_rad.copy()
    start[0], goal[0] = -0.8, 0.8
    hand = panda.link_poses(panda.home_position_rad)["panda_hand"][:3, 3]
    world = CollisionWorld(panda, padding_m=0.0)
    world.set_objects([SceneObject("plate", "box", tuple(hand), size_m=(0.1, 0.002, 0.1))])
    planner = MotionPlanner(panda, world, PlannerConfig(edge_resolution_rad=2.0, path_check_resolution_rad=path_check_rad))
    assert world.motion_valid(start, goal, 2.0) and not world.motion_valid(start, goal, 0.01)
    outcome = planner.plan(PlanProblem(start, goal, allowed_planning_time_s=0.5, seed=0))
    if path_check_rad == 0.0:
        assert outcome.status is PlanStatus.SUCCESS
        np.testing.assert_array_equal(outcome.path, [start, goal])  # the 2 rad check lets it through
        return
    assert outcome.status is PlanStatus.SUCCESS, outcome.detail
    assert len(outcome.path) > 2 and world.path_valid(outcome.path, 0.01)


def test_the_recheck_trusts_what_the_shortcut_accepted(panda: RobotModel) -> None:
    """At the edge resolution, a segment the shortcut's check accepted is not checked again."""
    planner = MotionPlanner(panda, CollisionWorld(panda, padding_m=0.0), PlannerConfig())
    home = panda.home_position_rad
    raw = np.array([home, home + 0.3, home - 0.3, home + 0.1])
    asked: list[tuple[tuple[float, ...], tuple[float, ...]]] = []

    def free(a: np.ndarray, b: np.ndarray) -> bool:
        asked.append((tuple(a), tuple(b)))
        return True

    outcome = planner._finish(PlanProblem(home, raw[-1], seed=0), raw, raw[-1:], free, "rrtconnect", 0.0,  # noqa: SLF001
                              np.random.default_rng(0))
    np.testing.assert_array_equal(outcome.path, raw[[0, -1]])
    assert asked[-1] == (tuple(home), tuple(raw[-1])) and len(set(asked)) == len(asked)


def test_a_shortcut_path_that_fails_the_recheck_falls_back_to_the_searched_path(panda: RobotModel) -> None:
    """Shortcutting keeps pieces of checked segments unchecked, so the re-check may refuse its
    path; the search's own path (here: a check that refuses those pieces) is returned. What the
    shortcut's own checks accepted is not asked again."""
    planner = MotionPlanner(panda, CollisionWorld(panda, padding_m=0.0), PlannerConfig())
    home = panda.home_position_rad
    raw = np.array([home, home + 0.3, home - 0.3, home + 0.1])
    raw_segments = {(tuple(a), tuple(b)) for a, b in zip(raw[:-1], raw[1:])}
    waypoints = {tuple(q) for q in raw}
    asked: list[tuple[tuple[float, ...], tuple[float, ...]]] = []

    def refuses_pieces(a: np.ndarray, b: np.ndarray) -> bool:
        """The raw path's segments pass, and connections between two points inside its
        segments (the shortcut's); none from a waypoint to such a point (the pieces it keeps)."""
        key = (tuple(a), tuple(b))
        asked.append(key)
        return key in raw_segments or not ({key[0], key[1]} & waypoints)

    problem = PlanProblem(home, raw[-1], seed=0)
    outcome = planner._finish(problem, raw, raw[-1:], refuses_pieces, "rrtconnect", 0.0,  # noqa: SLF001
                              np.random.default_rng(0))
    accepted = [key for key in asked if key not in raw_segments and not ({key[0], key[1]} & waypoints)]
    assert accepted  # the shortcut did change the path
    assert len(set(accepted)) == len(accepted)  # and the re-check trusted what it had accepted
    assert outcome.status is PlanStatus.SUCCESS
    np.testing.assert_array_equal(outcome.path, raw)
