"""Jerk-limited time parameterisation of a joint-space path with ruckig, and the trajectory type.

`JointTrajectory` is a sequence of pieces laid end to end in time; the path timing here, the
preemption blend (`blend_from_state`) and the stop trajectory in `stopping.py` produce one.
Joint quantities are in the units of the joints (rad or m), times in seconds.

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
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt
import ruckig

from robonav.pipeline.types import FloatArray, StateValidFn

JointState = tuple[FloatArray, FloatArray, FloatArray]
"""(q, qd, qdd): position, velocity and acceleration, each (n,)."""
"""state_valid(q (n,)) -> True when q is allowed (e.g. collision free)."""

_DUPLICATE_WAYPOINT_TOL = 1e-9
"""Waypoints closer than this in every joint [rad or m] count as the same point."""
DEFAULT_MAX_PATH_DEVIATION_RAD = 0.02
"""Default bound on the distance of a blended trajectory from the joint-space polyline [rad]."""
DEFAULT_MAX_BLEND_ANGLE_RAD = math.radians(120.0)
"""Corners turning by more than this stop at the waypoint [rad]."""
DEFAULT_CHECK_STEP_RAD = 0.01
"""`state_valid` is called at least every this much motion of any joint [rad]."""
_SHRINK_FACTOR = 0.6
"""Waypoint speeds of a segment that deviates too far are multiplied by this per iteration."""
_MAX_SHRINK_ITERATIONS = 12
"""After this many shrinks (0.6^12 ~ 0.002) a waypoint velocity is set to zero."""
_DEVIATION_SAMPLE_PERIOD_S = 0.002
"""Deviation is measured on samples this far apart in time (at least 16 per segment) [s]."""


class _Piece(Protocol):
    @property
    def duration_s(self) -> float: ...

    def at(self, t_s: float) -> JointState: ...

    def at_many(self, t_s: FloatArray) -> JointState:
        """(q, qd, qdd), each (M, n), at the (M,) times `t_s` in [0, duration_s]."""
        ...


@dataclass(frozen=True)
class TrajectoryLimits:
    """The (already scaled) limits a trajectory was timed with; blends and stops reuse them."""

    velocity: FloatArray
    """(n,) [rad/s]"""
    acceleration: FloatArray
    """(n,) [rad/s^2]"""
    jerk: FloatArray
    """(n,) [rad/s^3]"""


@dataclass(frozen=True)
class _LinePiece:
    """Straight segment q(t) = start_q + s(t) / length * delta_q.

    s is a 1-DoF ruckig profile from 0 to `length`, the largest joint travel |delta_q|_inf,
    starting and ending at the given path speeds with zero acceleration.
    """

    start_q: FloatArray
    end_q: FloatArray
    delta_q: FloatArray
    length: float
    profile: ruckig.Trajectory
    duration_s: float
    end_velocity: FloatArray

    def at(self, t_s: float) -> JointState:
        if t_s >= self.duration_s:
            # The stored end point, not start_q + s(T) / length * delta_q, which can be 1 ulp off.
            return self.end_q.copy(), self.end_velocity.copy(), np.zeros_like(self.delta_q)
        (s,), (sd,), (sdd,) = self.profile.at_time(t_s)
        direction = self.delta_q / self.length
        return self.start_q + s * direction, sd * direction, sdd * direction

    def at_many(self, t_s: FloatArray) -> JointState:
        # One 1-DoF ruckig call per time, the joint-space arithmetic once for all.
        path = np.array([[x[0] for x in self.profile.at_time(t)] for t in np.minimum(t_s, self.duration_s).tolist()])
        path = path.reshape(len(t_s), 3)
        direction = self.delta_q / self.length
        q = self.start_q + path[:, :1] * direction
        qd, qdd = path[:, 1:2] * direction, path[:, 2:3] * direction
        end = t_s >= self.duration_s
        q[end], qd[end], qdd[end] = self.end_q, self.end_velocity, 0.0
        return q, qd, qdd


@dataclass(frozen=True)
class _JointPiece:
    """An n-DoF ruckig trajectory, sampled as is; at its end the exact target state if given."""

    profile: ruckig.Trajectory
    duration_s: float
    end_state: JointState | None = None

    def at(self, t_s: float) -> JointState:
        if t_s >= self.duration_s and self.end_state is not None:
            # The stored target (a waypoint), not ruckig's end, which can be 1 ulp off.
            return tuple(x.copy() for x in self.end_state)  # type: ignore[return-value]
        q, qd, qdd = self.profile.at_time(min(t_s, self.duration_s))
        return np.array(q), np.array(qd), np.array(qdd)

    def at_many(self, t_s: FloatArray) -> JointState:
        states = np.array([self.profile.at_time(t) for t in np.minimum(t_s, self.duration_s).tolist()])
        states = states.reshape(len(t_s), 3, -1)
        q, qd, qdd = states[:, 0].copy(), states[:, 1].copy(), states[:, 2].copy()
        if self.end_state is not None:
            end = t_s >= self.duration_s
            q[end], qd[end], qdd[end] = self.end_state
        return q, qd, qdd


@dataclass(frozen=True)
class _HoldPiece:
    """Standing still at q for zero time (a path whose waypoints all coincide)."""

    q: FloatArray
    duration_s: float = 0.0

    def at(self, t_s: float) -> JointState:
        return self.q.copy(), np.zeros_like(self.q), np.zeros_like(self.q)

    def at_many(self, t_s: FloatArray) -> JointState:
        q = np.tile(self.q, (len(t_s), 1))
        return q, np.zeros_like(q), np.zeros_like(q)


class JointTrajectory:
    """A timed joint trajectory, immutable; sample it at any time in [0, duration_s]."""

    __slots__ = ("_pieces", "_starts_s", "_duration_s", "_dof", "_limits", "_max_deviation_rad",
                 "_waypoint_times_s")

    def __init__(self, pieces: Sequence[_Piece], dof: int, *, limits: TrajectoryLimits | None = None,
                 max_path_deviation_rad: float = 0.0, waypoint_times_s: FloatArray | None = None) -> None:
        """Lay `pieces` end to end in time. Use `time_parameterize` or `from_ruckig` instead."""
        if not pieces:
            raise ValueError("a JointTrajectory needs at least one piece")
        self._pieces = tuple(pieces)
        durations = np.array([p.duration_s for p in self._pieces], dtype=np.float64)
        self._starts_s = np.concatenate([[0.0], np.cumsum(durations)[:-1]])
        self._starts_s.setflags(write=False)
        self._duration_s = float(durations.sum())
        self._dof = dof
        self._limits = limits
        self._max_deviation_rad = float(max_path_deviation_rad)
        if waypoint_times_s is not None:
            waypoint_times_s = np.asarray(waypoint_times_s, dtype=np.float64).copy()
            waypoint_times_s.setflags(write=False)
        self._waypoint_times_s = waypoint_times_s

    @classmethod
    def from_ruckig(cls, trajectory: ruckig.Trajectory, *, limits: TrajectoryLimits | None = None) -> JointTrajectory:
        """Wrap one calculated n-DoF ruckig trajectory."""
        return cls([_JointPiece(trajectory, float(trajectory.duration))], int(trajectory.degrees_of_freedom),
                   limits=limits)

    @property
    def duration_s(self) -> float:
        """Total duration [s]."""
        return self._duration_s

    @property
    def dof(self) -> int:
        """Number of joints n."""
        return self._dof

    @property
    def limits(self) -> TrajectoryLimits | None:
        """The scaled limits the trajectory was timed with (None for a bare ruckig trajectory)."""
        return self._limits

    @property
    def max_path_deviation_rad(self) -> float:
        """Largest measured distance (Euclidean, joint space) from the path's polyline [rad]; 0 if unblended."""
        return self._max_deviation_rad

    @property
    def waypoint_times_s(self) -> FloatArray | None:
        """(P + 1,) read-only time of closest approach to each (deduplicated) waypoint [s], or None.

        Exactly at the waypoint for the ends and rest-to-rest corners; within
        `max_path_deviation_rad` of it for blended corners.
        """
        return self._waypoint_times_s

    @property
    def segment_start_times_s(self) -> FloatArray:
        """(M,) read-only start time of each piece (straight segment, corner blend) [s]."""
        return self._starts_s

    @property
    def pieces(self) -> tuple[_Piece, ...]:
        """The segments in time order (for splicing; sample the trajectory instead)."""
        return self._pieces

    def sample(self, t_s: float) -> JointState:
        """State at time `t_s` [s], clamped to [0, duration_s].

        Returns:
            (q, qd, qdd), each a new (n,) float64 array [rad, rad/s, rad/s^2 or m-based].
        """
        if not math.isfinite(t_s):
            raise ValueError(f"t_s must be finite, got {t_s}")
        t = min(max(float(t_s), 0.0), self._duration_s)
        # Ties go to the later piece, so a segment boundary samples the next segment's start.
        index = max(int(np.searchsorted(self._starts_s, t, side="right")) - 1, 0)
        piece = self._pieces[index]
        if t >= self._duration_s:
            # duration - start can fall 1 ulp short of the piece's own duration.
            return piece.at(piece.duration_s)
        return piece.at(t - float(self._starts_s[index]))

    def sample_many(self, t_s: npt.ArrayLike) -> JointState:
        """`sample` at every time of `t_s` (M,) at once, about five times faster per sample.

        Returns:
            q, qd, qdd, each (M, n).

        Raises:
            ValueError: a time that is not finite.
        """
        times = np.asarray(t_s, dtype=np.float64).reshape(-1)
        if not np.isfinite(times).all():
            raise ValueError("sample times must be finite")
        times = np.clip(times, 0.0, self._duration_s)
        index = np.maximum(np.searchsorted(self._starts_s, times, side="right") - 1, 0)
        # `sample`'s end rule: at or past the end, the last piece at its own duration.
        at_end = times >= self._duration_s
        index[at_end] = len(self._pieces) - 1
        local = times - self._starts_s[index]
        local[at_end] = self._pieces[-1].duration_s
        out = tuple(np.empty((len(times), self._dof)) for _ in range(3))
        for i in np.unique(index).tolist():
            rows = index == i
            for target, values in zip(out, self._pieces[i].at_many(local[rows])):
                target[rows] = values
        return out  # type: ignore[return-value]

    def sample_uniform(self, dt_s: float) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Sample every `dt_s` from 0, plus the end time when it is not on that grid.

        Args:
            dt_s: Sample period [s], > 0.

        Returns:
            t (M,), q (M, n), qd (M, n), qdd (M, n); t[0] = 0 and t[-1] = duration_s.
        """
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s must be a finite number > 0, got {dt_s}")
        n_steps = int(math.floor(self._duration_s / dt_s + 1e-9))
        times = np.arange(n_steps + 1, dtype=np.float64) * dt_s
        if self._duration_s - times[-1] > 1e-12:
            times = np.append(times, self._duration_s)
        else:
            times[-1] = self._duration_s
        q, qd, qdd = self.sample_many(times)
        return times, q, qd, qdd


def validate_joint_vector(values: npt.ArrayLike, name: str, dof: int, *, positive: bool = False) -> FloatArray:
    """Return `values` as a finite (dof,) float64 array (all > 0 if `positive`), or raise ValueError naming it."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.shape != (dof,):
        raise ValueError(f"{name} must have shape ({dof},), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} contains NaN or inf values: {arr.tolist()}")
    if positive and not (arr > 0).all():
        raise ValueError(f"{name} must be > 0 for every joint, got {arr.tolist()}")
    return arr


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
        return JointTrajectory([_HoldPiece(q)], dof, limits=limits, waypoint_times_s=np.zeros(1))
    for arr in kept:
        arr.setflags(write=False)
    corners = _Corners(kept, limits, max_path_deviation_rad, max_blend_angle_rad)
    if state_valid is not None:
        # Rest-to-rest corners are on the polyline, which the planner checked; a blend that
        # leaves it into an invalid state is dropped, which slows (and re-checks) its neighbours.
        unchecked = set(corners.blended())
        while unchecked:
            invalid = [w for w in sorted(unchecked)
                       if not _piece_valid(corners.blends[w], state_valid, limits, check_step_rad)]
            unchecked = set()
            for w in invalid:
                unchecked |= corners.drop(w)
            unchecked &= set(corners.blended())
    return corners.trajectory()


def blend_from_state(
    trajectory: JointTrajectory,
    q: npt.ArrayLike,
    qd: npt.ArrayLike,
    qdd: npt.ArrayLike,
    *,
    limits: TrajectoryLimits | None = None,
) -> JointTrajectory:
    """Start `trajectory` from a moving state: its first segment is replaced by a ruckig blend.

    The blend goes from (q, qd, qdd) to the state at the end of the first segment (waypoint 1
    with its velocity, or the goal at rest for a single-segment path) with all joints
    time-synchronised; the rest of the trajectory is unchanged. The result starts exactly at
    (q, qd, qdd), so it can replace a running trajectory without a jump in p, v or a. A state
    outside the limits is first braked back inside them by ruckig.

    Args:
        trajectory: A trajectory from `time_parameterize`.
        q: (n,) current commanded position [rad].
        qd: (n,) current commanded velocity [rad/s].
        qdd: (n,) current commanded acceleration [rad/s^2].
        limits: Scaled limits for the blend; default the trajectory's own.

    Returns:
        The spliced trajectory.

    Raises:
        ValueError: malformed state, or no limits given nor stored in the trajectory.
        RuntimeError: ruckig failed.
    """
    dof = trajectory.dof
    start = tuple(validate_joint_vector(x, name, dof) for x, name in ((q, "q"), (qd, "qd"), (qdd, "qdd")))
    limits = limits or trajectory.limits
    if limits is None:
        raise ValueError("blend_from_state needs limits: the trajectory carries none")
    first = trajectory.pieces[0]
    target = first.at(first.duration_s)
    blend = _ruckig_piece(start, target, limits, f"blend from q={start[0].tolist()}")  # type: ignore[arg-type]
    shift_s = blend.duration_s - first.duration_s
    times = None if trajectory.waypoint_times_s is None else np.maximum(trajectory.waypoint_times_s[1:] + shift_s, 0.0)
    return JointTrajectory([blend, *trajectory.pieces[1:]], dof, limits=limits,
                           max_path_deviation_rad=trajectory.max_path_deviation_rad, waypoint_times_s=times)


def polyline_deviation(q: npt.ArrayLike, path: npt.ArrayLike) -> FloatArray:
    """Euclidean joint-space distance of each sample to the nearest point of the polyline.

    Args:
        q: (M, n) samples [rad].
        path: (K, n) waypoints [rad], K >= 1.

    Returns:
        (M,) distances [rad].
    """
    samples = np.atleast_2d(np.asarray(q, dtype=np.float64))
    points = np.atleast_2d(np.asarray(path, dtype=np.float64))
    if points.shape[0] == 1:
        return np.linalg.norm(samples - points[0], axis=1)
    best = np.full(samples.shape[0], np.inf)
    for a, b in zip(points[:-1], points[1:]):
        best = np.minimum(best, _distance_to_segment(samples, a, b))
    return best


def _distance_to_segment(samples: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    delta = b - a
    length_sq = float(delta @ delta)
    if length_sq == 0.0:
        return np.linalg.norm(samples - a, axis=1)
    s = np.clip((samples - a) @ delta / length_sq, 0.0, 1.0)
    return np.linalg.norm(samples - a - s[:, None] * delta, axis=1)


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


class _Corners:
    """The blend at each interior waypoint and the straight pieces between them.

    Corner w (1 <= w <= P - 1) is passed at speed `speeds[w]` [rad/s, Euclidean] on a ruckig
    blend from B_in = W_w - r_w d_in to B_out = W_w + r_w d_out, velocity along each segment
    at both ends and zero acceleration; speed 0 means rest exactly at W_w. The straight piece
    of segment w runs along the line from W_w + r_w d_w to W_w+1 - r_w+1 d_w.
    """

    def __init__(self, kept: FloatArray, limits: TrajectoryLimits, bound_rad: float, max_angle_rad: float) -> None:
        self.kept = kept
        self.limits = limits
        self.bound_rad = bound_rad
        count = kept.shape[0]
        deltas = np.diff(kept, axis=0)
        self.lengths = np.linalg.norm(deltas, axis=1)
        self.units = deltas / self.lengths[:, None]
        # Along segment w the joints move in fixed proportion, so each joint's limit bounds
        # the Euclidean path speed and acceleration by limit_j / |d_j|.
        with np.errstate(divide="ignore"):
            self.line_speed = np.min(limits.velocity / np.abs(self.units), axis=1)
            self.line_accel = np.min(limits.acceleration / np.abs(self.units), axis=1)
        self.speeds = np.zeros(count)
        self.radii = np.zeros(count)
        self.blends: dict[int, _JointPiece] = {}
        self.errors = np.zeros(count)
        if bound_rad > 0:
            for w in range(1, count - 1):
                turn = math.acos(float(np.clip(self.units[w - 1] @ self.units[w], -1.0, 1.0)))
                if turn <= max_angle_rad:
                    self._fit(w, 0.999 * min(self.line_speed[w - 1], self.line_speed[w]))
            self._limit_by_segments()

    def blended(self) -> list[int]:
        return sorted(self.blends)

    def _fit(self, w: int, speed: float) -> None:
        """The fastest blend at corner w not faster than `speed` within the bound, or none."""
        d_in, d_out = self.units[w - 1], self.units[w]
        room = 0.45 * min(self.lengths[w - 1], self.lengths[w])
        ramp_s = float(np.max(self.limits.acceleration / self.limits.jerk))
        for _ in range(_MAX_SHRINK_ITERATIONS):
            # Time to turn the velocity at full acceleration, and the distance covered meanwhile.
            turn_s = float(np.max(speed * np.abs(d_out - d_in) / self.limits.acceleration)) + 2 * ramp_s
            radius = min(0.5 * speed * turn_s, room)
            piece = self._blend_piece(w, speed, radius)
            error = self._error(piece, w)
            if error <= self.bound_rad:
                self.speeds[w], self.radii[w], self.blends[w], self.errors[w] = speed, radius, piece, error
                return
            speed *= _SHRINK_FACTOR
        self.drop(w)

    def drop(self, w: int) -> set[int]:
        """Make corner w rest to rest; return the corners whose blends changed because of it."""
        self.speeds[w] = self.radii[w] = self.errors[w] = 0.0
        self.blends.pop(w, None)
        before = self.speeds.copy()
        self._limit_by_segments()
        return {int(c) for c in np.flatnonzero(self.speeds != before)}

    def _limit_by_segments(self) -> None:
        """Forward-backward pass: each straight piece can change the speed only as fast as its limits allow."""
        changed = True
        while changed:
            changed = False
            for w in range(len(self.lengths)):
                straight = self.lengths[w] - self.radii[w] - self.radii[w + 1]
                # 0.8: margin for the jerk-limited ramps that a pure acceleration bound ignores.
                reach = 2.0 * 0.8 * self.line_accel[w] * max(straight, 0.0)
                for a, b in ((w, w + 1), (w + 1, w)):
                    if self.speeds[b] ** 2 > self.speeds[a] ** 2 + reach + 1e-12:
                        self._refit(b, math.sqrt(self.speeds[a] ** 2 + reach))
                        changed = True

    def _refit(self, w: int, speed: float) -> None:
        if speed <= 1e-6:
            self.speeds[w] = self.radii[w] = self.errors[w] = 0.0
            self.blends.pop(w, None)
            return
        # A slower blend turns in a shorter distance, so it stays within the bound.
        self._fit(w, speed)

    def _blend_piece(self, w: int, speed: float, radius: float) -> _JointPiece:
        d_in, d_out = self.units[w - 1], self.units[w]
        corner = self.kept[w]
        zero = np.zeros_like(corner)
        start = (corner - radius * d_in, speed * d_in, zero)
        end = (corner + radius * d_out, speed * d_out, zero)
        return _ruckig_piece(start, end, self.limits, f"the blend at waypoint {w}")

    def _error(self, piece: _JointPiece, w: int) -> float:
        """Largest of the distance from the polyline and the closest approach to the waypoint."""
        samples = _piece_samples(piece, _DEVIATION_SAMPLE_PERIOD_S)
        deviation = float(polyline_deviation(samples, self.kept[w - 1: w + 2]).max())
        miss = float(np.linalg.norm(samples - self.kept[w], axis=1).min())
        return max(deviation, miss)

    def trajectory(self) -> JointTrajectory:
        pieces: list[_Piece] = []
        waypoint_times = [0.0]
        elapsed = 0.0
        for w in range(len(self.lengths)):
            start_q = self.kept[w] + self.radii[w] * self.units[w]
            end_q = self.kept[w + 1] - self.radii[w + 1] * self.units[w]
            line = _line_piece(start_q, end_q, self.limits.velocity, self.limits.acceleration, self.limits.jerk,
                               start_speed=self.speeds[w], end_speed=self.speeds[w + 1],
                               exact_end=self.kept[w + 1] if self.radii[w + 1] == 0 else None)
            pieces.append(line)
            elapsed += line.duration_s
            if w + 1 in self.blends:
                blend = self.blends[w + 1]
                pieces.append(blend)
                waypoint_times.append(elapsed + self._closest_time(blend, w + 1))
                elapsed += blend.duration_s
            else:
                waypoint_times.append(elapsed)
        return JointTrajectory(pieces, self.kept.shape[1], limits=self.limits,
                               max_path_deviation_rad=float(self.errors.max()),
                               waypoint_times_s=np.array(waypoint_times))

    def _closest_time(self, piece: _JointPiece, w: int) -> float:
        times = np.linspace(0.0, piece.duration_s, 64)
        distances = [np.linalg.norm(piece.at(float(t))[0] - self.kept[w]) for t in times]
        return float(times[int(np.argmin(distances))])


def _ruckig_piece(start: JointState, end: JointState, limits: TrajectoryLimits, what: str) -> _JointPiece:
    dof = start[0].shape[0]
    otg = ruckig.Ruckig(dof)
    inp = ruckig.InputParameter(dof)
    inp.synchronization = ruckig.Synchronization.Time
    inp.current_position, inp.current_velocity, inp.current_acceleration = (x.tolist() for x in start)
    inp.target_position, inp.target_velocity, inp.target_acceleration = (x.tolist() for x in end)
    inp.max_velocity = limits.velocity.tolist()
    inp.max_acceleration = limits.acceleration.tolist()
    inp.max_jerk = limits.jerk.tolist()
    profile = ruckig.Trajectory(dof)
    try:
        result = otg.calculate(inp, profile)
    except ruckig.RuckigError as exc:  # the python binding raises on most failures
        raise RuntimeError(f"ruckig failed to time {what}") from exc
    if result not in (ruckig.Result.Working, ruckig.Result.Finished):
        raise RuntimeError(f"ruckig failed to time {what}: {result}")
    end_state = tuple(np.array(x, dtype=np.float64) for x in end)
    return _JointPiece(profile, float(profile.duration), end_state)  # type: ignore[arg-type]


def _piece_samples(piece: _Piece, dt_s: float, minimum: int = 16) -> FloatArray:
    count = max(minimum, int(math.ceil(piece.duration_s / dt_s)) + 1)
    return np.array([piece.at(float(t))[0] for t in np.linspace(0.0, piece.duration_s, count)])


def _piece_valid(piece: _Piece, state_valid: StateValidFn, limits: TrajectoryLimits, check_step_rad: float) -> bool:
    # No joint moves faster than its velocity limit, so this period bounds every joint's step.
    dt_s = check_step_rad / float(limits.velocity.max())
    return all(state_valid(q) for q in _piece_samples(piece, dt_s, minimum=2))


def _line_piece(
    start_q: FloatArray, end_q: FloatArray, v_max: FloatArray, a_max: FloatArray, j_max: FloatArray, *,
    start_speed: float = 0.0, end_speed: float = 0.0, exact_end: FloatArray | None = None,
) -> _LinePiece:
    """A straight piece from start_q to end_q, entered and left at the given Euclidean speeds [rad/s]."""
    # One ruckig DoF along the segment instead of n DoFs with Synchronization.Phase:
    # ruckig silently falls back to time synchronisation (leaving the straight line) when
    # the limiting joint's profile, scaled to the other joints, would break one of their
    # limits -- about a quarter of random Panda segments. For q = start + s / L * delta,
    # joint i's limits bound s by limit_i * L / |delta_i|; the minimum over joints is the
    # exact feasible set for straight-line motion. Measuring s in units of the largest
    # travel L keeps these bounds near the joint limits however short the segment is.
    delta_q = end_q - start_q
    travel = np.abs(delta_q)
    length = float(travel.max())
    moving = travel > 0
    with np.errstate(over="ignore"):
        ratio = length / travel[moving]  # >= 1, exactly 1 for the leading joint: never all inf
    otg = ruckig.Ruckig(1)
    inp = ruckig.InputParameter(1)
    # Path speeds are Euclidean; s runs in units of the largest joint travel.
    to_s = length / float(np.linalg.norm(delta_q)) if (start_speed or end_speed) else 0.0
    inp.current_position = [0.0]
    inp.target_position = [length]
    inp.current_velocity = [start_speed * to_s]
    inp.target_velocity = [end_speed * to_s]
    inp.max_velocity = [float(np.min(v_max[moving] * ratio))]
    inp.max_acceleration = [float(np.min(a_max[moving] * ratio))]
    inp.max_jerk = [float(np.min(j_max[moving] * ratio))]
    profile = ruckig.Trajectory(1)
    try:
        result = otg.calculate(inp, profile)
    except ruckig.RuckigError as exc:  # the python binding raises on most failures
        raise RuntimeError(f"ruckig failed to time the segment {start_q.tolist()} -> {end_q.tolist()}") from exc
    if result not in (ruckig.Result.Working, ruckig.Result.Finished):
        raise RuntimeError(f"ruckig failed to time the segment {start_q.tolist()} -> {end_q.tolist()}: {result}")
    start = start_q.copy()
    end = (end_q if exact_end is None else exact_end).copy()
    end_velocity = end_speed * to_s / length * delta_q if end_speed else np.zeros_like(delta_q)
    for arr in (start, end, delta_q, end_velocity):
        arr.setflags(write=False)
    return _LinePiece(start, end, delta_q, length, profile, float(profile.duration), end_velocity)
