"""Jerk-limited time parameterisation of a joint-space path with ruckig (the trajectory type is in
`trajectory.py`, the corner blends in `blending.py`).

How a path is timed (ruckig's free version only: one calculation per segment, no
intermediate-waypoint feature):

1. Every interior waypoint gets a velocity along the bisector of its two segments, as fast as
   the joint velocity limits and the segment lengths allow, and zero where the corner is
   sharper than `max_blend_angle_rad`. Every waypoint's acceleration is zero.
2. Each segment is one n-DoF ruckig trajectory from (p_i, v_i, 0) to (p_i+1, v_i+1, 0) with
   `Synchronization.Time`; a segment that starts and ends at rest is timed along the straight
   line instead (exactly on the polyline).
3. The trajectory is sampled and its distance to the joint-space polyline measured; the
   velocities at both ends of a segment that strays further than `max_path_deviation_rad`
   are shrunk and the segment re-timed, down to rest-to-rest, which has zero deviation.
4. With a `state_valid` callback (the collision world), every blended segment is sampled every
   `check_step_rad` of motion; a segment with an invalid sample is re-timed rest to rest
   (the planner checked the polyline) and its neighbours re-checked.

The trajectory therefore passes through every waypoint exactly and ends exactly at the goal
at rest.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from robonav.pipeline.trajectory.blending import Corners
from robonav.pipeline.trajectory.trajectory import (
    HoldPiece,
    JointTrajectory,
    TrajectoryLimits,
    piece_valid,
    validate_joint_vector,
)
from robonav.pipeline.types import FloatArray, StateValidFn

_DUPLICATE_WAYPOINT_TOL = 1e-9
"""Waypoints closer than this in every joint [rad or m] count as the same point."""
DEFAULT_MAX_PATH_DEVIATION_RAD = 0.02
"""Default bound on the distance of a blended trajectory from the joint-space polyline [rad]."""
DEFAULT_MAX_BLEND_ANGLE_RAD = math.radians(120.0)
"""Corners turning by more than this stop at the waypoint [rad]."""
DEFAULT_CHECK_STEP_RAD = 0.01
"""`state_valid` is called at least every this much motion of any joint [rad]."""


def _validate_scaling(value: float, name: str) -> float:
    if not (math.isfinite(value) and 0.0 < value <= 1.0):
        raise ValueError(f"{name} must be in (0, 1], got {value}")
    return float(value)


def scaled_limits(
    dof: int,
    *,
    max_velocity: npt.ArrayLike,
    max_acceleration: npt.ArrayLike,
    max_jerk: npt.ArrayLike,
    velocity_scaling: float = 1.0,
    acceleration_scaling: float = 1.0,
) -> TrajectoryLimits:
    """Validate per-joint limits and scale them (jerk is scaled like acceleration).

    Raises:
        ValueError: a limit is not a finite positive (dof,) vector, or a factor is outside (0, 1].
    """
    v_scale = _validate_scaling(velocity_scaling, "velocity_scaling")
    a_scale = _validate_scaling(acceleration_scaling, "acceleration_scaling")
    return TrajectoryLimits(
        velocity=validate_joint_vector(max_velocity, "max_velocity", dof, positive=True) * v_scale,
        acceleration=validate_joint_vector(max_acceleration, "max_acceleration", dof, positive=True) * a_scale,
        jerk=validate_joint_vector(max_jerk, "max_jerk", dof, positive=True) * a_scale,
    )


def time_parameterize(
    path: npt.ArrayLike,
    *,
    max_velocity: npt.ArrayLike,
    max_acceleration: npt.ArrayLike,
    max_jerk: npt.ArrayLike,
    velocity_scaling: float = 1.0,
    acceleration_scaling: float = 1.0,
    max_path_deviation_rad: float = DEFAULT_MAX_PATH_DEVIATION_RAD,
    max_blend_angle_rad: float = DEFAULT_MAX_BLEND_ANGLE_RAD,
    state_valid: StateValidFn | None = None,
    check_step_rad: float = DEFAULT_CHECK_STEP_RAD,
) -> JointTrajectory:
    """Time a joint-space polyline jerk-limited, passing through interior waypoints without stopping.

    See the module docstring for the method. `max_path_deviation_rad=0` gives the old
    behaviour: rest to rest at every waypoint, exactly on the polyline.

    Args:
        path: (K, n) waypoints [rad or m], K >= 1. Consecutive duplicates (closer than 1e-9
            in every joint) are merged; the first and last waypoints are kept exactly.
        max_velocity: (n,) joint velocity limits, > 0.
        max_acceleration: (n,) joint acceleration limits, > 0.
        max_jerk: (n,) joint jerk limits, > 0.
        velocity_scaling: Factor in (0, 1] on the velocity limits.
        acceleration_scaling: Factor in (0, 1] on the acceleration and jerk limits.
        max_path_deviation_rad: Bound on the Euclidean joint-space distance of any sample
            from the polyline [rad], >= 0; 0 disables blending.
        max_blend_angle_rad: Corners turning by more than this (angle between the two segment
            directions) are passed at rest [rad], in [0, pi].
        state_valid: Optional check of a configuration (e.g. collision free). Blended segments
            with an invalid sample fall back to rest to rest.
        check_step_rad: Largest motion of any joint between two `state_valid` samples [rad], > 0.

    Returns:
        The trajectory; duration 0 when all waypoints coincide.

    Raises:
        ValueError: malformed path, limits, scaling factors or bounds.
        RuntimeError: ruckig could not time a segment (not expected for valid inputs).
    """
    waypoints = np.asarray(path, dtype=np.float64)
    if waypoints.ndim != 2 or waypoints.shape[0] < 1 or waypoints.shape[1] < 1:
        raise ValueError(f"path must have shape (K, n) with K >= 1 and n >= 1, got {waypoints.shape}")
    if not np.isfinite(waypoints).all():
        raise ValueError("path contains NaN or inf values")
    dof = waypoints.shape[1]
    limits = scaled_limits(dof, max_velocity=max_velocity, max_acceleration=max_acceleration, max_jerk=max_jerk,
                           velocity_scaling=velocity_scaling, acceleration_scaling=acceleration_scaling)
    if not (math.isfinite(max_path_deviation_rad) and max_path_deviation_rad >= 0):
        raise ValueError(f"max_path_deviation_rad must be a finite number >= 0, got {max_path_deviation_rad}")
    if not (0.0 <= max_blend_angle_rad <= math.pi):
        raise ValueError(f"max_blend_angle_rad must be in [0, pi], got {max_blend_angle_rad}")
    if not (math.isfinite(check_step_rad) and check_step_rad > 0):
        raise ValueError(f"check_step_rad must be a finite number > 0, got {check_step_rad}")

    kept = _merge_duplicate_waypoints(waypoints)
    if kept.shape[0] == 1:
        q = kept[0].copy()
        q.setflags(write=False)
        return JointTrajectory([HoldPiece(q)], dof, limits=limits, waypoint_times_s=np.zeros(1))
    for arr in kept:
        arr.setflags(write=False)
    corners = Corners(kept, limits, max_path_deviation_rad, max_blend_angle_rad)
    if state_valid is not None:
        # Rest-to-rest corners are on the polyline, which the planner checked; a blend that
        # leaves it into an invalid state is dropped, which slows (and re-checks) its neighbours.
        unchecked = set(corners.blended())
        while unchecked:
            invalid = [w for w in sorted(unchecked)
                       if not piece_valid(corners.blends[w], state_valid, limits, check_step_rad)]
            unchecked = set()
            for w in invalid:
                unchecked |= corners.drop(w)
            unchecked &= set(corners.blended())
    return corners.trajectory()


def _merge_duplicate_waypoints(waypoints: FloatArray) -> FloatArray:
    kept = [waypoints[0]]
    for q in waypoints[1:]:
        if np.abs(q - kept[-1]).max() > _DUPLICATE_WAYPOINT_TOL:
            kept.append(q)
    if len(kept) > 1:
        # The goal must be reached exactly, so a near-duplicate goal replaces its neighbour.
        kept[-1] = waypoints[-1]
    elif np.abs(waypoints[-1] - waypoints[0]).max() > 0:
        kept.append(waypoints[-1])
    return np.array(kept)
