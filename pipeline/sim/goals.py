"""Goals for campaigns: random joint goals that a camera-built map can allow, some needing detours.

A single camera with "fill below surfaces" perceives each object as solid down to the table,
so goals are drawn, and judged feasible, against that view of the truth: every object
replaced by its world bounding box extended down to the floor (`perceivable_objects`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.planning.motion_planner import MotionPlanner, PlanProblem
from robonav.pipeline.planning.result import PlanStatus
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.types import FloatArray

_CORNER_SIGNS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)


def perceivable_objects(objects: tuple[SceneObject, ...] | list[SceneObject], floor_z_m: float) -> tuple[SceneObject, ...]:
    """Each object as an axis-aligned box from its lowest-seen floor up to its top: what a
    camera above sees as solid when everything below a seen surface counts as occupied.

    Args:
        objects: The true obstacles, world frame.
        floor_z_m: Height the boxes extend down to [m] (the map's floor).
    """
    boxes = []
    for obj in objects:
        center, half = obj.local_bounds_m
        pose = obj.world_from_object
        corners = (center + _CORNER_SIGNS * half) @ pose[:3, :3].T + pose[:3, 3]
        low, high = corners.min(axis=0), corners.max(axis=0)
        low[2] = min(low[2], floor_z_m)
        size = np.maximum(high - low, 1e-4)
        boxes.append(SceneObject(obj.name, "box", tuple((0.5 * (low + high)).tolist()), size_m=tuple(size.tolist())))
    return tuple(boxes)


@dataclass(frozen=True)
class GoalSample:
    """A sampled joint goal."""

    q: FloatArray
    """(n,) goal configuration [rad]."""
    clearance_m: float
    """Distance from the unpadded robot to the world at the goal [m]."""
    straight_blocked: bool
    """The straight joint-space segment from the start is blocked: the goal needs a detour."""
    link_position_m: FloatArray
    """(3,) position of the reference link (the end effector) at the goal [m]."""


def sample_goal(world: CollisionWorld, rng: np.random.Generator, start: npt.ArrayLike, *, link: str,
                region_min_m: npt.ArrayLike, region_max_m: npt.ArrayLike, min_clearance_m: float,
                want_blocked: bool | None = None, min_move_rad: float = 0.5, edge_resolution_rad: float = 0.02,
                attempts: int = 400) -> GoalSample | None:
    """Draw a collision-free joint goal with `link` inside a box, well clear of the world.

    Args:
        world: The world goals must be free in (its padding applies to the collision check).
        rng: Source of randomness.
        start: (n,) the configuration the robot will start from [rad].
        link: Link whose position must lie in the region (e.g. the end effector).
        region_min_m: (3,) lower corner of the region, world frame [m].
        region_max_m: (3,) upper corner [m].
        min_clearance_m: Smallest unpadded robot-world distance at the goal [m].
        want_blocked: True: only goals whose straight segment from `start` is blocked;
            False: only goals it reaches directly; None: either.
        min_move_rad: The goal differs from `start` by at least this in some joint [rad].
        edge_resolution_rad: Step for the straight-segment check [rad].
        attempts: Draws before giving up.

    Returns:
        A goal, or None if none of `attempts` draws qualified.
    """
    robot = world.robot
    q_start = robot.validate_q(np.asarray(start, dtype=np.float64), "start")
    low, high = robot.lower_limits_rad, robot.upper_limits_rad
    # Stay 5 % inside the limits: goals at a limit make every plan graze it.
    margin = 0.05 * (high - low)
    region_low, region_high = np.asarray(region_min_m, float), np.asarray(region_max_m, float)
    for _ in range(attempts):
        # A continuous joint's goal on the turn nearest the start: where the planner ends it,
        # so the move, the straight-line test and the recorded goal are the arm's own.
        q = robot.nearest_turn_rad(rng.uniform(low + margin, high - margin), q_start)
        if np.max(np.abs(q - q_start)) < min_move_rad:
            continue
        position = robot.frame_pose(q, link)[:3, 3]
        if np.any(position < region_low) or np.any(position > region_high):
            continue
        if world.in_collision(q):
            continue
        clearance = world.clearance_m(q)
        if clearance < min_clearance_m:
            continue
        blocked = not world.motion_valid(q_start, q, edge_resolution_rad)
        if want_blocked is not None and blocked != want_blocked:
            continue
        return GoalSample(q, float(clearance), blocked, position.copy())
    return None


def point_along_path(path: npt.ArrayLike, fraction: float) -> FloatArray:
    """The configuration at `fraction` (0..1) of a joint path's length, linearly interpolated."""
    arr = np.asarray(path, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[0] < 1:
        raise ValueError(f"path must have shape (K >= 1, n), got {arr.shape}")
    lengths = np.linalg.norm(np.diff(arr, axis=0), axis=1)
    total = float(lengths.sum())
    if total == 0.0:
        return arr[0].copy()
    target = min(max(fraction, 0.0), 1.0) * total
    cumulative = np.concatenate([[0.0], np.cumsum(lengths)])
    i = min(int(np.searchsorted(cumulative, target, side="right")) - 1, len(lengths) - 1)
    t = 0.0 if lengths[i] == 0 else (target - cumulative[i]) / lengths[i]
    return arr[i] + t * (arr[i + 1] - arr[i])


@dataclass(frozen=True)
class Intruder:
    """A box scripted to slide onto an arm's trajectory."""

    start: SceneObject
    """The box where it waits (world frame)."""
    target_m: tuple[float, float, float]
    """Where its center comes to rest: where `link` passes at `target_time_s` [m]."""
    target_time_s: float
    """When the arm's link would be at the target, from the trajectory's start [s]."""
    lead_s: float
    """Time from the box coming to rest until any link first comes within the threat
    distance of it [s]: what perception, the map and a stop have to work with."""


def intruder_for_trajectory(robot: RobotModel, times_s: npt.ArrayLike, q_rad: npt.ArrayLike, *, link: str,
                            slide_s: float, min_lead_s: float, name: str = "intruder", size_m: float = 0.1,
                            offsets_m: tuple[float, ...] = (0.4, 0.55, 0.7), clearance_m: float = 0.05,
                            threat_m: float = 0.1,
                            reject: Callable[[SceneObject], bool] | None = None) -> Intruder | None:
    """A box that slides onto a timed trajectory as the arm starts, early enough to be avoidable.

    The box starts moving at t = 0 and rests after `slide_s` where `link` will pass later.
    The earliest such place is taken whose lead (rest until the first link comes within
    `threat_m` of the box) is at least `min_lead_s`, and whose slide keeps `clearance_m` from
    the arm at every moment. The box comes in horizontally across the link's direction of
    travel (either side) or from above.

    Args:
        robot: The arm.
        times_s: (M,) sample times of the trajectory, from 0 [s].
        q_rad: (M, n) joint positions at those times [rad].
        link: The link whose future position the box blocks (e.g. the end effector).
        slide_s: Duration of the slide [s].
        min_lead_s: Smallest acceptable lead [s].
        reject: Resting places (the box there) this returns True for are skipped, e.g. those
            that would make the goal unreachable.

    Returns:
        The intruder, or None when the trajectory is too short or every start touches the arm.
    """
    times = np.asarray(times_s, dtype=np.float64)
    states = np.asarray(q_rad, dtype=np.float64)
    positions = np.array([robot.frame_pose(q, link)[:3, 3] for q in states])
    near = CollisionWorld(robot, padding_m=clearance_m)
    threat = CollisionWorld(robot, padding_m=threat_m)
    box = SceneObject(name, "box", (0.0, 0.0, 0.0), size_m=(size_m, size_m, size_m))
    during_slide = np.nonzero(times <= slide_s)[0]
    for k in np.nonzero(times >= slide_s + min_lead_s)[0]:
        target = positions[k]
        threat.set_objects([box.with_pose(_translation(target))])
        touching = [i for i in range(k + 1) if times[i] >= slide_s and threat.in_collision(states[i])]
        first = times[touching[0]] if touching else times[k]
        if first - slide_s < min_lead_s:
            continue
        if reject is not None and reject(box.with_pose(_translation(target))):
            continue
        step = positions[min(k + 1, len(positions) - 1)] - positions[max(k - 1, 0)]
        across = np.array([-step[1], step[0], 0.0]) if np.linalg.norm(step[:2]) > 1e-6 else np.array([0.0, 1.0, 0.0])
        across /= np.linalg.norm(across)
        for offset in offsets_m:
            for direction in (across, -across, np.array([0.0, 0.0, 1.0])):
                start = target + offset * direction
                if _slide_touches(near, box, start, target, times, states, during_slide, slide_s):
                    continue
                return Intruder(box.with_pose(_translation(start)), (float(target[0]), float(target[1]), float(target[2])),
                                float(times[k]), float(first - slide_s))
    return None


def _slide_touches(world: CollisionWorld, box: SceneObject, start: FloatArray, target: FloatArray, times: FloatArray,
                   states: FloatArray, during_slide: npt.NDArray[np.intp], slide_s: float) -> bool:
    """Whether the box, where it is at each moment of its slide, comes within the world's padding of the arm."""
    for i in during_slide:
        fraction = min(times[i] / slide_s, 1.0) if slide_s > 0 else 1.0
        world.set_objects([box.with_pose(_translation(start + fraction * (target - start)))])
        if world.in_collision(states[i]):
            return True
    return False


def _translation(position_m: FloatArray) -> FloatArray:
    pose = np.eye(4)
    pose[:3, 3] = position_m
    return pose


def goal_region(objects: tuple[SceneObject, ...] | list[SceneObject], workspace_min_m: npt.ArrayLike,
                workspace_max_m: npt.ArrayLike, *, above_table_m: float = 0.05) -> tuple[FloatArray, FloatArray]:
    """The box end-effector goals are drawn in: the perception workspace, from `above_table_m`
    over the top of the object named `table` (if any) up. Returns (min (3,), max (3,)) [m]."""
    top_z = max((o.position_m[2] + o.local_bounds_m[1][2] for o in objects if o.name == "table"), default=-np.inf)
    low = np.array(workspace_min_m, dtype=np.float64)
    low[2] = max(low[2], top_z + above_table_m)
    return low, np.array(workspace_max_m, dtype=np.float64)


def draw_goal_sequence(world: CollisionWorld, reference: MotionPlanner, rng: np.random.Generator, start: npt.ArrayLike,
                       *, count: int, link: str, region_min_m: npt.ArrayLike, region_max_m: npt.ArrayLike,
                       min_clearance_m: float, seed: int, draws: int = 20,
                       planning_time_s: float = 2.0) -> list[FloatArray]:
    """`count` goals visited in turn from `start`, each reachable from the one before.

    Each goal is drawn as `sample_goal` does in `world` (padded by the caller to what a map
    can add), preferring goals whose straight joint-space way from the previous one is blocked,
    so the sequence needs detours; a goal counts only if the `reference` planner, which plans
    in `world`, reaches it from the previous one within `planning_time_s`.

    Raises:
        ValueError: no reachable goal in `draws` draws for some position in the sequence.
    """
    goals: list[FloatArray] = []
    previous = np.asarray(start, dtype=np.float64)
    for index in range(count):
        for draw in range(draws):
            want_blocked: bool | None = True if draw < draws // 2 else None
            sample = sample_goal(world, rng, previous, link=link, region_min_m=region_min_m, region_max_m=region_max_m,
                                 min_clearance_m=min_clearance_m, want_blocked=want_blocked)
            if sample is None:
                continue
            outcome = reference.plan(PlanProblem(start_rad=previous, goals_rad=sample.q,
                                                 allowed_planning_time_s=planning_time_s, seed=seed + 100 * index + draw))
            if outcome.status is PlanStatus.SUCCESS:
                goals.append(sample.q)
                previous = sample.q
                break
        else:
            raise ValueError(f"no reachable goal {index} for link {link} in {draws} draws "
                             f"(region {np.round(region_min_m, 3).tolist()} .. {np.round(region_max_m, 3).tolist()})")
    return goals
