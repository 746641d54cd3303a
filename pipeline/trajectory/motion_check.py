"""The executor's check of a motion before it streams: the timed trajectory against the world, like a plan.

MoveIt's plan execution checks a trajectory against the planning scene before it runs it; a
client can send any path to `executor/execute`, so the executor does the same. The motion is
what will really be commanded, the time-parameterized trajectory with its corner blends, sampled
so that no joint moves more than the planner's edge resolution between two samples. Each sample
gets the planner's test: joint limits, padded links against the (inflated) occupancy map and
the scene objects, bare links against each other, attached objects.

On the straight lines of the path the check asks about exactly the states the planner
checked: each sample there is moved to the nearest of the planner's states on that segment
(`k / steps` of it, `collision/edges.step_count` at the planner's resolution), so a path the
planner accepted on the same map is never refused for grazing the padding between two of the
planner's states (it happened: a demo plan's third segment touched the padding at 1/200 of its
length, between two of the planner's 23 states, and the motion's samples fell on it). Corner
blends, off the polyline, are sampled in time.

One exception, also the planner's: an arm that braked in front of an obstacle often rests with
a padded link inside the inflated map, and the planner then plans a way out
(`planning/start_escape.py`). When the start state collides with the map alone, samples within
`escape_radius_rad` of the start (every joint) are held to the planner's rule for that way out
instead: padded links off the voxels the cameras saw (before inflation), bare links off objects
and each other. The same rule decides a state's validity inside and outside that box wherever
it occurs on the motion, so a check by state (`MotionRule.valid`, for dropping corner blends
while timing) and the check of the whole motion agree.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from robonav.pipeline.collision.edges import step_count
from robonav.pipeline.collision.world import OCCUPANCY, CollisionWorld
from robonav.pipeline.planning.start_escape import way_out_touches
from robonav.pipeline.trajectory.trajectory import JointTrajectory
from robonav.pipeline.types import FloatArray, StateValidFn

ON_LINE_RAD = 1e-9
"""A sample this close to a segment of the path (every joint) lies on it: a straight piece."""


@dataclass(frozen=True)
class MotionViolation:
    """The first sample of a motion that may not be commanded."""

    index: int
    """Index of the sample, 0 being the start."""
    time_from_start_s: float
    """When the trajectory reaches it [s]."""
    positions_rad: FloatArray
    """(n,) the state [rad]."""
    pairs: tuple[str, ...]
    """'link|object' pairs in collision (object: a link, a scene object or 'occupancy';
    attached objects come first in their pairs), empty for a joint-limit violation."""
    limit_violations: tuple[str, ...]
    """Joints outside their limits, in words; empty for a collision."""
    samples: int
    """Samples checked up to and including this one."""


def motion_samples(trajectory: JointTrajectory, resolution_rad: float) -> tuple[FloatArray, FloatArray]:
    """Times (M,) [s] and states (M, n) of `trajectory`, no joint moving more than
    `resolution_rad` between two consecutive samples (the velocity limits bound each step)."""
    if not resolution_rad > 0:
        raise ValueError(f"resolution_rad must be > 0, got {resolution_rad}")
    limits = trajectory.limits
    if trajectory.duration_s <= 0:
        q, _, _ = trajectory.sample(0.0)
        return np.zeros(1), q[None]
    # Without its limits the trajectory's own samples bound the speed; a fine grid finds it.
    speed = float(np.max(limits.velocity)) if limits is not None else \
        float(np.max(np.abs(trajectory.sample_uniform(min(0.001, trajectory.duration_s))[2]))) * 1.01
    dt_s = resolution_rad / max(speed, 1e-9)
    times, q, _, _ = trajectory.sample_uniform(min(dt_s, trajectory.duration_s))
    return times, q


def on_plan_samples(states_rad: FloatArray, path_rad: FloatArray | None, resolution_rad: float) -> FloatArray:
    """`states_rad` (M, n) with each state that lies on a segment of `path_rad` (K, n) moved to the
    nearest state the planner checks on that segment; states off the polyline stay (see the
    module docstring). None: no path, the states as they are."""
    states = np.array(states_rad, dtype=np.float64)
    if path_rad is None or len(path_rad) < 2:
        return states
    path = np.asarray(path_rad, dtype=np.float64)
    starts, deltas = path[:-1], np.diff(path, axis=0)  # (P, n)
    lengths_sq = np.einsum("pn,pn->p", deltas, deltas)
    moving = lengths_sq > 0
    starts, deltas, lengths_sq = starts[moving], deltas[moving], lengths_sq[moving]
    if len(starts) == 0:
        return states
    steps = np.array([step_count(a, a + d, resolution_rad) for a, d in zip(starts, deltas)])
    # Position along each segment and distance from it, for every state and segment: (M, P).
    along = np.clip(np.einsum("mpn,pn->mp", states[:, None, :] - starts[None], deltas) / lengths_sq, 0.0, 1.0)
    off = np.max(np.abs(starts[None] + along[..., None] * deltas[None] - states[:, None, :]), axis=2)
    segment = np.argmin(off, axis=1)
    on_line = off[np.arange(len(states)), segment] <= ON_LINE_RAD
    k = np.round(along[np.arange(len(states)), segment] * steps[segment]) / steps[segment]
    snapped = starts[segment] + k[:, None] * deltas[segment]
    states[on_line] = snapped[on_line]
    return states


class MotionRule:
    """Which states an executed motion may pass through (see the module docstring)."""

    def __init__(self, world: CollisionWorld, states_rad: FloatArray, *, escape_radius_rad: float) -> None:
        """Args:
            world: The planner's world as the executor holds it (map, objects, attached objects).
            states_rad: (M, n) the motion's samples, row 0 its start [rad]. The way-out test
                gathers only voxels near them, so it is exact for these states and the ones
                close to them (a slower corner blend of the same path), not for any state.
            escape_radius_rad: The planner's `start_escape_rad`; 0: no way out of the padding.
        """
        self._world = world
        self._robot = world.robot
        states = np.asarray(states_rad, dtype=np.float64).reshape(-1, self._robot.dof)
        self._start = states[0].copy()
        self._radius = float(escape_radius_rad)
        self._way_out = None
        if self._radius > 0:
            pairs = world.collisions(self._start)
            if pairs and all(other == OCCUPANCY for _, other in pairs):
                self._way_out = way_out_touches(world, states)

    @property
    def escapes_start(self) -> bool:
        """The start collides with the map alone: states near it follow the way-out rule."""
        return self._way_out is not None

    def limit_violations(self, q: FloatArray) -> list[str]:
        return self._robot.check_joint_limits(q)

    def pairs(self, q: FloatArray) -> list[str]:
        """'link|object' pairs that make `q` unacceptable (empty: acceptable as far as collisions go)."""
        if self._way_out is not None and float(np.max(np.abs(q - self._start))) <= self._radius:
            if not self._way_out(q):
                return []
            # Name what the bare arm touches, and the map when only the seen voxels were reached.
            pairs = self._world.collisions(q, padded=False)
            return [f"{a}|{b}" for a, b in pairs] or [f"{a}|{b}" for a, b in self._world.collisions(q) if b == OCCUPANCY]
        return [f"{a}|{b}" for a, b in self._world.collisions(q)]

    def valid(self, q: FloatArray) -> bool:
        """Within the joint limits and free by the rule."""
        return not self.limit_violations(q) and not self.pairs(q)


def check_motion(world: CollisionWorld, trajectory: JointTrajectory, *, resolution_rad: float,
                 escape_radius_rad: float, path_rad: FloatArray | None = None) -> MotionViolation | None:
    """The first sample of `trajectory` outside the joint limits or in collision, or None.

    Args:
        world: The world to check against.
        trajectory: The motion as it will be commanded.
        resolution_rad: Largest joint step between samples (the planner's path check resolution) [rad].
        escape_radius_rad: The planner's start escape radius [rad] (see the module docstring).
        path_rad: (K, n) the path `trajectory` was timed from: samples on its lines are the
            planner's states (`on_plan_samples`); None: every sample as timed.
    """
    times, states = motion_samples(trajectory, resolution_rad)
    return _first_violation(world, times, on_plan_samples(states, path_rad, resolution_rad), escape_radius_rad)


def _first_violation(world: CollisionWorld, times: FloatArray, states: FloatArray,
                     escape_radius_rad: float) -> MotionViolation | None:
    rule = MotionRule(world, states, escape_radius_rad=escape_radius_rad)
    for i, q in enumerate(states):
        limits = rule.limit_violations(q)
        pairs = [] if limits else rule.pairs(q)
        if limits or pairs:
            return MotionViolation(index=i, time_from_start_s=float(times[i]), positions_rad=q.copy(), pairs=tuple(pairs),
                                   limit_violations=tuple(limits), samples=i + 1)
    return None


@dataclass(frozen=True)
class CheckedTiming:
    trajectory: JointTrajectory
    """The motion to stream when `violation` is None, else the last one tried."""
    violation: MotionViolation | None
    samples: int
    """Samples of `trajectory` checked (all of them when it passed)."""


def checked_timing(world: CollisionWorld, timing: Callable[[StateValidFn | None], JointTrajectory], *,
                   resolution_rad: float, escape_radius_rad: float, path_rad: FloatArray | None = None) -> CheckedTiming:
    """Time a path and check the motion; a corner blend that fails is dropped (rest on its waypoint).

    Shortcut paths hug obstacles at their corners, and a blend cuts the corner: the planner
    checked the polyline, not the blend. When the blended motion fails, the path is timed again
    with every blend that leaves the rule dropped (`time_parameterize`'s `state_valid`), which
    puts those corners back on the polyline, and checked again.

    Args:
        world: The world to check against.
        timing: Times the path; its argument is the state check for blends (None: blend freely).
        resolution_rad: Largest joint step between checked samples [rad].
        escape_radius_rad: The planner's start escape radius [rad].
        path_rad: (K, n) the path `timing` times (see `check_motion`).

    Returns:
        The trajectory to stream without a violation, or the last trajectory tried and its first violation.
    """
    trajectory = timing(None)
    times, states = motion_samples(trajectory, resolution_rad)
    states = on_plan_samples(states, path_rad, resolution_rad)
    violation = _first_violation(world, times, states, escape_radius_rad)
    if violation is not None and trajectory.max_path_deviation_rad > 0.0:
        rule = MotionRule(world, states, escape_radius_rad=escape_radius_rad)
        trajectory = timing(rule.valid)
        times, states = motion_samples(trajectory, resolution_rad)
        states = on_plan_samples(states, path_rad, resolution_rad)
        violation = _first_violation(world, times, states, escape_radius_rad)
    return CheckedTiming(trajectory, violation, len(states) if violation is None else violation.samples)
