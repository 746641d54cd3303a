"""Jerk-limited time parameterisation of a joint-space path with ruckig, and the trajectory type.

`JointTrajectory` is a sequence of ruckig pieces laid end to end in time; both the path
timing here and the stop trajectory in `stopping.py` produce one. Joint quantities are in
the units of the joints (rad or m), times in seconds.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt
import ruckig

FloatArray = npt.NDArray[np.float64]
JointState = tuple[FloatArray, FloatArray, FloatArray]
"""(q, qd, qdd): position, velocity and acceleration, each (n,)."""

_DUPLICATE_WAYPOINT_TOL = 1e-9
"""Waypoints closer than this in every joint [rad or m] count as the same point."""


class _Piece(Protocol):
    @property
    def duration_s(self) -> float: ...

    def at(self, t_s: float) -> JointState: ...


@dataclass(frozen=True)
class _LinePiece:
    """Rest-to-rest straight segment q(t) = start_q + s(t) / length * delta_q.

    s is a 1-DoF ruckig profile from 0 to `length`, the largest joint travel |delta_q|_inf.
    """

    start_q: FloatArray
    end_q: FloatArray
    delta_q: FloatArray
    length: float
    profile: ruckig.Trajectory
    duration_s: float

    def at(self, t_s: float) -> JointState:
        if t_s >= self.duration_s:
            # The stored waypoint, not start_q + s(T) / length * delta_q, which can be 1 ulp off.
            return self.end_q.copy(), np.zeros_like(self.delta_q), np.zeros_like(self.delta_q)
        (s,), (sd,), (sdd,) = self.profile.at_time(t_s)
        direction = self.delta_q / self.length
        return self.start_q + s * direction, sd * direction, sdd * direction


@dataclass(frozen=True)
class _JointPiece:
    """An n-DoF ruckig trajectory, sampled as is."""

    profile: ruckig.Trajectory
    duration_s: float

    def at(self, t_s: float) -> JointState:
        q, qd, qdd = self.profile.at_time(min(t_s, self.duration_s))
        return np.array(q), np.array(qd), np.array(qdd)


@dataclass(frozen=True)
class _HoldPiece:
    """Standing still at q for zero time (a path whose waypoints all coincide)."""

    q: FloatArray
    duration_s: float = 0.0

    def at(self, t_s: float) -> JointState:
        return self.q.copy(), np.zeros_like(self.q), np.zeros_like(self.q)


class JointTrajectory:
    """A timed joint trajectory, immutable; sample it at any time in [0, duration_s]."""

    __slots__ = ("_pieces", "_starts_s", "_duration_s", "_dof")

    def __init__(self, pieces: Sequence[_Piece], dof: int) -> None:
        """Lay `pieces` end to end in time. Use `time_parameterize` or `from_ruckig` instead."""
        if not pieces:
            raise ValueError("a JointTrajectory needs at least one piece")
        self._pieces = tuple(pieces)
        durations = np.array([p.duration_s for p in self._pieces], dtype=np.float64)
        self._starts_s = np.concatenate([[0.0], np.cumsum(durations)[:-1]])
        self._starts_s.setflags(write=False)
        self._duration_s = float(durations.sum())
        self._dof = dof

    @classmethod
    def from_ruckig(cls, trajectory: ruckig.Trajectory) -> JointTrajectory:
        """Wrap one calculated n-DoF ruckig trajectory."""
        return cls([_JointPiece(trajectory, float(trajectory.duration))], int(trajectory.degrees_of_freedom))

    @property
    def duration_s(self) -> float:
        """Total duration [s]."""
        return self._duration_s

    @property
    def dof(self) -> int:
        """Number of joints n."""
        return self._dof

    @property
    def segment_start_times_s(self) -> FloatArray:
        """(P,) read-only start time of each segment [s].

        For `time_parameterize`, segment i leaves waypoint i (after merging duplicates) at
        rest, so these plus `duration_s` are the times the trajectory is at the waypoints.
        """
        return self._starts_s

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
        states = [self.sample(float(t)) for t in times]
        q, qd, qdd = (np.array([s[i] for s in states]).reshape(len(times), self._dof) for i in range(3))
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


def time_parameterize(
    path: npt.ArrayLike,
    *,
    max_velocity: npt.ArrayLike,
    max_acceleration: npt.ArrayLike,
    max_jerk: npt.ArrayLike,
    velocity_scaling: float = 1.0,
    acceleration_scaling: float = 1.0,
) -> JointTrajectory:
    """Time a joint-space polyline with jerk-limited, rest-to-rest motion along each segment.

    Every segment starts and ends at rest and moves along the straight line between its
    waypoints, so the robot follows the planned (collision-checked) polyline exactly; the
    price is stopping at every waypoint. Blending through waypoints is later work.

    Args:
        path: (K, n) waypoints [rad or m], K >= 1. Consecutive duplicates (closer than 1e-9
            in every joint) are merged; the first and last waypoints are kept exactly.
        max_velocity: (n,) joint velocity limits, > 0.
        max_acceleration: (n,) joint acceleration limits, > 0.
        max_jerk: (n,) joint jerk limits, > 0.
        velocity_scaling: Factor in (0, 1] on the velocity limits.
        acceleration_scaling: Factor in (0, 1] on the acceleration and jerk limits.

    Returns:
        The trajectory; duration 0 when all waypoints coincide.

    Raises:
        ValueError: malformed path, limits or scaling factors.
    """
    waypoints = np.asarray(path, dtype=np.float64)
    if waypoints.ndim != 2 or waypoints.shape[0] < 1 or waypoints.shape[1] < 1:
        raise ValueError(f"path must have shape (K, n) with K >= 1 and n >= 1, got {waypoints.shape}")
    if not np.isfinite(waypoints).all():
        raise ValueError("path contains NaN or inf values")
    dof = waypoints.shape[1]
    v_scale = _validate_scaling(velocity_scaling, "velocity_scaling")
    a_scale = _validate_scaling(acceleration_scaling, "acceleration_scaling")
    v_max = validate_joint_vector(max_velocity, "max_velocity", dof, positive=True) * v_scale
    a_max = validate_joint_vector(max_acceleration, "max_acceleration", dof, positive=True) * a_scale
    j_max = validate_joint_vector(max_jerk, "max_jerk", dof, positive=True) * a_scale

    kept = _merge_duplicate_waypoints(waypoints)
    if kept.shape[0] == 1:
        q = kept[0].copy()
        q.setflags(write=False)
        return JointTrajectory([_HoldPiece(q)], dof)
    pieces = [_line_piece(start, end, v_max, a_max, j_max) for start, end in zip(kept[:-1], kept[1:])]
    return JointTrajectory(pieces, dof)


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


def _line_piece(
    start_q: FloatArray, end_q: FloatArray, v_max: FloatArray, a_max: FloatArray, j_max: FloatArray
) -> _LinePiece:
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
    inp.current_position = [0.0]
    inp.target_position = [length]
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
    start, end = start_q.copy(), end_q.copy()
    for arr in (start, end, delta_q):
        arr.setflags(write=False)
    return _LinePiece(start, end, delta_q, length, profile, float(profile.duration))
