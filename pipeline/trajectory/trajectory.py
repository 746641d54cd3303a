"""The timed joint trajectory: pieces laid end to end in time, sampled at any time.

`time_parameterize` (timing.py) times a path into one, `blend_from_state` (blending.py) splices
a moving start onto one, and `stop_trajectory` (stopping.py) brakes into one. Joint quantities
are in the units of the joints (rad or m), times in seconds.
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

KinematicState = tuple[FloatArray, FloatArray, FloatArray]
"""(q, qd, qdd): position, velocity and acceleration, each (n,)."""


class Piece(Protocol):
    @property
    def duration_s(self) -> float: ...

    def at(self, t_s: float) -> KinematicState: ...

    def at_many(self, t_s: FloatArray) -> KinematicState:
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
class LinePiece:
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

    def at(self, t_s: float) -> KinematicState:
        if t_s >= self.duration_s:
            # The stored end point, not start_q + s(T) / length * delta_q, which can be 1 ulp off.
            return self.end_q.copy(), self.end_velocity.copy(), np.zeros_like(self.delta_q)
        (s,), (sd,), (sdd,) = self.profile.at_time(t_s)
        direction = self.delta_q / self.length
        return self.start_q + s * direction, sd * direction, sdd * direction

    def at_many(self, t_s: FloatArray) -> KinematicState:
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
class JointPiece:
    """An n-DoF ruckig trajectory, sampled as is; at its end the exact target state if given."""

    profile: ruckig.Trajectory
    duration_s: float
    end_state: KinematicState | None = None

    def at(self, t_s: float) -> KinematicState:
        if t_s >= self.duration_s and self.end_state is not None:
            # The stored target (a waypoint), not ruckig's end, which can be 1 ulp off.
            return tuple(x.copy() for x in self.end_state)  # type: ignore[return-value]
        q, qd, qdd = self.profile.at_time(min(t_s, self.duration_s))
        return np.array(q), np.array(qd), np.array(qdd)

    def at_many(self, t_s: FloatArray) -> KinematicState:
        states = np.array([self.profile.at_time(t) for t in np.minimum(t_s, self.duration_s).tolist()])
        states = states.reshape(len(t_s), 3, -1)
        q, qd, qdd = states[:, 0].copy(), states[:, 1].copy(), states[:, 2].copy()
        if self.end_state is not None:
            end = t_s >= self.duration_s
            q[end], qd[end], qdd[end] = self.end_state
        return q, qd, qdd


@dataclass(frozen=True)
class HoldPiece:
    """Standing still at q: for zero time (a path whose waypoints all coincide), or for the dwell
    before a motion from rest (`with_start_dwell`)."""

    q: FloatArray
    duration_s: float = 0.0

    def at(self, t_s: float) -> KinematicState:
        return self.q.copy(), np.zeros_like(self.q), np.zeros_like(self.q)

    def at_many(self, t_s: FloatArray) -> KinematicState:
        q = np.tile(self.q, (len(t_s), 1))
        return q, np.zeros_like(q), np.zeros_like(q)


class JointTrajectory:
    """A timed joint trajectory, immutable; sample it at any time in [0, duration_s]."""

    __slots__ = ("_pieces", "_starts_s", "_duration_s", "_dof", "_limits", "_max_deviation_rad",
                 "_waypoint_times_s")

    def __init__(self, pieces: Sequence[Piece], dof: int, *, limits: TrajectoryLimits | None = None,
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
        return cls([JointPiece(trajectory, float(trajectory.duration))], int(trajectory.degrees_of_freedom),
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
    def pieces(self) -> tuple[Piece, ...]:
        """The segments in time order (for splicing; sample the trajectory instead)."""
        return self._pieces

    def sample(self, t_s: float) -> KinematicState:
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

    def sample_many(self, t_s: npt.ArrayLike) -> KinematicState:
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


def with_start_dwell(trajectory: JointTrajectory, dwell_s: float) -> JointTrajectory:
    """`trajectory` preceded by `dwell_s` at rest where it starts (its waypoint times moved with it).

    Raises:
        ValueError: `dwell_s` negative or not finite.
    """
    if not (math.isfinite(dwell_s) and dwell_s >= 0):
        raise ValueError(f"dwell_s must be a finite number >= 0, got {dwell_s}")
    if dwell_s == 0:
        return trajectory
    start_q = trajectory.sample(0.0)[0]
    times = trajectory.waypoint_times_s
    return JointTrajectory([HoldPiece(start_q, float(dwell_s)), *trajectory.pieces], trajectory.dof,
                           limits=trajectory.limits, max_path_deviation_rad=trajectory.max_path_deviation_rad,
                           waypoint_times_s=None if times is None else times + dwell_s)


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


def ruckig_piece(start: KinematicState, end: KinematicState, limits: TrajectoryLimits, what: str) -> JointPiece:
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
    return JointPiece(profile, float(profile.duration), end_state)  # type: ignore[arg-type]


def piece_samples(piece: Piece, dt_s: float, minimum: int = 16) -> FloatArray:
    count = max(minimum, int(math.ceil(piece.duration_s / dt_s)) + 1)
    return np.array([piece.at(float(t))[0] for t in np.linspace(0.0, piece.duration_s, count)])


def piece_valid(piece: Piece, state_valid: StateValidFn, limits: TrajectoryLimits, check_step_rad: float) -> bool:
    # No joint moves faster than its velocity limit, so this period bounds every joint's step.
    dt_s = check_step_rad / float(limits.velocity.max())
    return all(state_valid(q) for q in piece_samples(piece, dt_s, minimum=2))


def line_piece(
    start_q: FloatArray, end_q: FloatArray, v_max: FloatArray, a_max: FloatArray, j_max: FloatArray, *,
    start_speed: float = 0.0, end_speed: float = 0.0, exact_end: FloatArray | None = None,
) -> LinePiece:
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
    return LinePiece(start, end, delta_q, length, profile, float(profile.duration), end_velocity)
