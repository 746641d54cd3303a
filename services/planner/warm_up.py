"""Before the planner declares itself alive: compile and run everything a first plan runs.

Numba compiles a kernel the first time it is called with a new signature (from the on-disk
cache when one is there: `robonav precompile`); without this, the first plan request paid for
it, several seconds holding the GIL. A worker plans twice in a small world of its own making:
around a box (objects only: the sphere-first search, shortcutting, re-validation, clearance),
around the same box as occupancy voxels (the exact search against an octree), and around those
voxels given with a clearance, as a map that says its inflation is planned (`plan_worker.py`);
then it calls the remaining collision queries once each and builds the exact link geometry
contacts are confirmed on (a UR5 gripper mesh's BVH: about 50 ms each). Then its world is
emptied again.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import octomap

from robonav.pipeline.planning.motion_planner import PlanProblem
from robonav.pipeline.planning.shortcut import shortcut_path
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.types import FloatArray
from robonav.services.planner.plan_worker import PlanWorker

log = logging.getLogger("robonav.planner")

VOXEL_M = 0.02
BOX_M = 0.1


def warm_up_worker(worker: PlanWorker, *, seed: int = 0) -> float:
    """Plan in `worker`'s world around a box, then around voxels (bare, then with a clearance), then empty the world; returns
    the time it took [s]. Failures to find a path are fine: the code they ran is compiled."""
    started = time.perf_counter()
    robot, world, planner = worker.world.robot, worker.world, worker.planner
    start, goal, box_center = _detour(worker)
    box = SceneObject(name="warm_up_box", type="box", position_m=tuple(box_center), size_m=(BOX_M, BOX_M, BOX_M))
    world.set_objects([box])
    outcomes = [planner.plan(PlanProblem(start_rad=start, goals_rad=goal, allowed_planning_time_s=2.0, seed=seed))]
    world.clear_objects()
    centers = _cube_of_voxels(box_center)
    world.set_octree(_octree(centers), VOXEL_M, centers)
    outcomes.append(planner.plan(PlanProblem(start_rad=start, goals_rad=goal, allowed_planning_time_s=2.0, seed=seed)))
    # A map that says its inflation: the tiered sphere kernels of the clearance released near the ends.
    world.set_octree(_octree(centers), VOXEL_M, centers, clearance_m=VOXEL_M)
    outcomes.append(planner.plan(PlanProblem(start_rad=start, goals_rad=goal, allowed_planning_time_s=2.0, seed=seed)))
    # What a plan may run besides the search: every collision query once, and the shortcut kernels
    # on a path that has something to shorten (the searches above may have gone straight).
    world.set_objects([box])
    world.build_exact_shapes()
    middle = 0.5 * (start + goal)
    world.collisions(middle)
    world.collisions(middle, padded=False)
    world.touches_cubes(start, centers, VOXEL_M)
    world.clearance_m(start)
    world.min_clearance_m(np.array([start, goal]))
    world.motion_valid(start, goal, planner.config.edge_resolution_rad)
    world.path_valid(np.array([start, middle, goal]), planner.config.edge_resolution_rad)
    zigzag = np.array([start, start + 0.1, middle, goal - 0.1, goal])
    zigzag = np.clip(zigzag, robot.lower_limits_rad, robot.upper_limits_rad)
    shortcut_path(zigzag, motion_valid=lambda a, b: True, rng=np.random.default_rng(seed), iterations=5)
    worker.forget()
    elapsed = time.perf_counter() - started
    log.info("warm-up: %s in %.1f s", ", ".join(f"{o.status.name.lower()} ({o.search or 'no search'})" for o in outcomes),
             elapsed)
    return elapsed


def _detour(worker: PlanWorker) -> tuple[FloatArray, FloatArray, FloatArray]:
    """A start and goal at the robot's home, turned about the first joint, and the spot where
    the end effector passes halfway: a box there blocks the straight joint-space motion."""
    robot = worker.world.robot
    link = robot.config.end_effector_link
    start = robot.home_position_rad.copy()
    goal = start.copy()
    goal[0] = float(np.clip(start[0] + 1.2, robot.lower_limits_rad[0], robot.upper_limits_rad[0]))
    if abs(goal[0] - start[0]) < 0.6:  # the first joint cannot turn that way
        goal[0] = float(np.clip(start[0] - 1.2, robot.lower_limits_rad[0], robot.upper_limits_rad[0]))
    middle = 0.5 * (start + goal)
    return start, goal, robot.frame_pose(middle, link)[:3, 3]


def _cube_of_voxels(center_m: FloatArray) -> FloatArray:
    steps = (np.arange(int(round(BOX_M / VOXEL_M))) + 0.5) * VOXEL_M - BOX_M / 2
    grid = np.stack(np.meshgrid(steps, steps, steps, indexing="ij"), axis=-1).reshape(-1, 3)
    # On the voxel grid (centers at odd multiples of half a voxel), as a map's voxels are.
    return (np.floor((grid + center_m) / VOXEL_M) + 0.5) * VOXEL_M


def _octree(centers_m: FloatArray) -> bytes:
    tree = octomap.OcTree(VOXEL_M)
    for center in centers_m:
        tree.updateNode(center.astype(np.float64), True)
    return tree.writeBinary()
