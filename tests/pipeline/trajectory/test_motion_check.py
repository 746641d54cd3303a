"""The executor's motion check: the timed trajectory against the world, the planner's start escape, blends."""

from __future__ import annotations

import numpy as np
import octomap

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.perception.maps.octree import inflation_offsets
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.trajectory.motion_check import check_motion, checked_timing, motion_samples, on_plan_samples
from robonav.pipeline.trajectory.timing import time_parameterize
from robonav.pipeline.types import StateValidFn
from robonav.services.config import load_config

CFG = load_config()
ROBOT = RobotModel.from_config(CFG.robot)
HOME = ROBOT.home_position_rad
RESOLUTION = CFG.planner.edge_resolution_rad
VOXEL_M = 0.02


def _timed(path: np.ndarray, state_valid: StateValidFn | None = None, deviation: float = 0.02):  # noqa: ANN202
    return time_parameterize(path, max_velocity=ROBOT.velocity_limits, max_acceleration=ROBOT.acceleration_limits,
                             max_jerk=ROBOT.jerk_limits, velocity_scaling=0.5, acceleration_scaling=0.5,
                             max_path_deviation_rad=deviation, state_valid=state_valid)


def _world(*objects: SceneObject) -> CollisionWorld:
    world = CollisionWorld(ROBOT, padding_m=CFG.robot.padding_m)
    world.set_objects(objects)
    return world


def _set_map(world: CollisionWorld, seen_m: np.ndarray) -> None:
    """The map perception would publish for these voxels: the octree inflated by one voxel."""
    keys = np.unique(np.floor(seen_m / VOXEL_M).astype(np.int64), axis=0)
    inflated = np.unique((keys[:, None, :] + inflation_offsets(CFG.perception.inflation_m, VOXEL_M)[None]).reshape(-1, 3), axis=0)
    tree = octomap.OcTree(VOXEL_M)
    tree.updateNodes((inflated + 0.5) * VOXEL_M, True)
    world.set_octree(tree.writeBinary(), VOXEL_M, (keys + 0.5) * VOXEL_M)


def test_samples_are_never_further_apart_than_the_resolution() -> None:
    trajectory = _timed(np.array([HOME, HOME + [1.0, 0.3, 0, -0.3, 0, 0.2, 0], HOME + [0.2, 0, 0.5, 0, 0, 0, 0]]))
    times, states = motion_samples(trajectory, RESOLUTION)
    assert times[0] == 0.0 and times[-1] == trajectory.duration_s
    assert np.max(np.abs(np.diff(states, axis=0))) <= RESOLUTION + 1e-9


def test_a_motion_through_an_object_names_the_first_state_and_the_pairs() -> None:
    goal = HOME + np.array([1.2, 0, 0, 0, 0, 0, 0])
    halfway = ROBOT.frame_pose(HOME + np.array([0.6, 0, 0, 0, 0, 0, 0]), "panda_hand")[:3, 3]
    box = SceneObject(name="box", type="box", position_m=tuple(halfway), size_m=(0.1, 0.1, 0.1))
    trajectory = _timed(np.array([HOME, goal]))
    assert check_motion(_world(), trajectory, resolution_rad=RESOLUTION, escape_radius_rad=0.1) is None
    world = _world(box)
    violation = check_motion(world, trajectory, resolution_rad=RESOLUTION, escape_radius_rad=0.1)
    assert violation is not None and violation.index > 0 and not violation.limit_violations
    assert 0 < violation.time_from_start_s < trajectory.duration_s
    assert any(pair.endswith("|box") for pair in violation.pairs), violation.pairs
    # It is the first: every earlier sample is free.
    times, states = motion_samples(trajectory, RESOLUTION)
    assert violation.time_from_start_s == times[violation.index]
    assert all(not world.collisions(q) for q in states[:violation.index])


def test_a_blend_that_cuts_into_the_padding_falls_back_to_the_waypoint() -> None:
    """The polyline clears a small object inside its corner; the blend that cuts the corner would not."""
    corner = HOME + np.array([0.8, 0, 0, 0, 0, 0, 0])
    path = np.array([HOME, corner, corner + [0, 0.6, 0, 0, 0, 0, 0]])
    wide = 0.2  # a generous blend bound, so the corner cut is centimetres, not millimetres

    blended = _timed(path, deviation=wide)
    _, states = motion_samples(blended, RESOLUTION)
    inner = states[np.argmin([np.abs(q - corner).max() for q in states])]
    assert np.abs(inner - corner).max() > 0.02, "the test path needs a blended corner"
    # A point of the hand's hull at the blend's innermost state that no state of the polyline reaches.
    free = _world()
    polyline = np.vstack([a + np.outer(np.linspace(0, 1, 200), b - a) for a, b in zip(path[:-1], path[1:])])
    pose = ROBOT.frame_pose(inner, "panda_hand")
    hull = ROBOT.link_collision_shapes["panda_hand"][0].hull_vertices @ pose[:3, :3].T + pose[:3, 3]
    nub = next((p for p in hull if free.touches_cubes(inner, p[None], 0.002)
                and not any(free.touches_cubes(q, p[None], 0.002) for q in polyline)), None)
    assert nub is not None, "no point of the hand's hull is reached by the blend alone"
    world = _world(SceneObject(name="nub", type="box", position_m=tuple(nub), size_m=(0.002, 0.002, 0.002)))
    assert world.path_valid(path, RESOLUTION / 4)
    violation = check_motion(world, blended, resolution_rad=RESOLUTION, escape_radius_rad=0.0)
    assert violation is not None and violation.pairs == ("panda_hand|nub",), violation

    checked = checked_timing(world, lambda valid: _timed(path, valid, deviation=wide), resolution_rad=RESOLUTION,
                             escape_radius_rad=0.0)
    assert checked.violation is None and checked.samples == len(motion_samples(checked.trajectory, RESOLUTION)[0])
    assert checked.trajectory.max_path_deviation_rad < blended.max_path_deviation_rad


def test_a_start_inside_the_padding_may_leave_it_as_the_planner_allows() -> None:
    """The hand rests with its padding inside the inflated map but off the voxel the camera saw:
    the way out is allowed (the planner's start escape); a motion that stays there is not."""
    hand = ROBOT.frame_pose(HOME, "panda_hand")[:3, 3]
    world = _world()
    for offset in np.arange(0.02, 0.2, 0.002):
        voxel = hand + np.array([0.0, 0.0, -offset])
        _set_map(world, voxel[None])
        if world.collisions(HOME) and not world.touches_cubes(HOME, world.seen_voxels_m, VOXEL_M):
            break
    else:
        raise AssertionError("found no voxel just inside the padding")
    up = HOME + np.array([0, -0.08, 0, 0.0, 0, 0, 0])
    away = _timed(np.array([HOME, up]))
    assert check_motion(world, away, resolution_rad=RESOLUTION, escape_radius_rad=0.1) is None
    violation = check_motion(world, away, resolution_rad=RESOLUTION, escape_radius_rad=0.0)
    assert violation is not None and violation.index == 0 and any(p.endswith("|occupancy") for p in violation.pairs)


def test_a_motion_out_of_the_joint_limits_is_a_violation() -> None:
    beyond = HOME.copy()
    beyond[3] = ROBOT.upper_limits_rad[3] + 0.05
    violation = check_motion(_world(), _timed(np.array([HOME, beyond])), resolution_rad=RESOLUTION, escape_radius_rad=0.1)
    assert violation is not None and violation.limit_violations and not violation.pairs
    assert "panda_joint4" in violation.limit_violations[0]


def test_on_the_lines_the_check_asks_about_the_planners_states() -> None:
    path = np.array([HOME, HOME + [0.5, 0.1, 0, 0, 0, 0, 0], HOME + [0.5, 0.1, 0.3, 0, 0, 0, 0]])
    on_line = path[0] + 0.37 * (path[1] - path[0])
    off_line = on_line + 0.01
    moved = on_plan_samples(np.array([on_line, off_line]), path, RESOLUTION)
    steps = 25  # ceil(0.5 / 0.02)
    np.testing.assert_allclose(moved[0], path[0] + round(0.37 * steps) / steps * (path[1] - path[0]), atol=1e-12)
    np.testing.assert_array_equal(moved[1], off_line)


def test_a_path_the_planner_accepts_is_accepted_on_the_same_world() -> None:
    """Whatever grazes lie between the planner's states, a rest-to-rest motion along a path that
    passes the planner's check passes the executor's (random boxes around random paths)."""
    rng = np.random.default_rng(5)
    checked = 0
    for _ in range(12):
        centers = rng.uniform([0.2, -0.5, 0.1], [0.7, 0.5, 0.8], size=(6, 3))
        world = _world(*(SceneObject(name=f"b{i}", type="box", position_m=tuple(c), size_m=(0.06, 0.06, 0.06))
                         for i, c in enumerate(centers)))
        path = np.vstack([HOME, HOME + rng.uniform(-0.6, 0.6, 7), HOME + rng.uniform(-0.6, 0.6, 7)])
        path = np.clip(path, ROBOT.lower_limits_rad, ROBOT.upper_limits_rad)
        if not world.path_valid(path, RESOLUTION):
            continue
        checked += 1
        trajectory = _timed(path, deviation=0.0)
        assert check_motion(world, trajectory, resolution_rad=RESOLUTION, escape_radius_rad=0.1, path_rad=path) is None
    assert checked >= 3
