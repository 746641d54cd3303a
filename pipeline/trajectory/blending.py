"""Corner blending and preemption: passing waypoints without stopping, and starting from a moving state.

A blended corner is one synchronised n-DoF ruckig profile from a point on the incoming segment
to one on the outgoing segment, as fast as the bound on the distance from the polyline
allows (`Corners`). A preemption replaces a trajectory's first segment by a ruckig profile
from the commanded (q, qd, qdd) (`blend_from_state`).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from robonav.pipeline.trajectory.trajectory import (
    JointPiece,
    JointTrajectory,
    Piece,
    TrajectoryLimits,
    line_piece,
    piece_samples,
    ruckig_piece,
    validate_joint_vector,
)
from robonav.pipeline.types import FloatArray

_SHRINK_FACTOR = 0.6
"""Waypoint speeds of a segment that deviates too far are multiplied by this per iteration."""
_MAX_SHRINK_ITERATIONS = 12
"""After this many shrinks (0.6^12 ~ 0.002) a waypoint velocity is set to zero."""
_DEVIATION_SAMPLE_PERIOD_S = 0.002
"""Deviation is measured on samples this far apart in time (at least 16 per segment) [s]."""


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
    blend = ruckig_piece(start, target, limits, f"blend from q={start[0].tolist()}")  # type: ignore[arg-type]
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


class Corners:
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
        self.blends: dict[int, JointPiece] = {}
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

    def _blend_piece(self, w: int, speed: float, radius: float) -> JointPiece:
        d_in, d_out = self.units[w - 1], self.units[w]
        corner = self.kept[w]
        zero = np.zeros_like(corner)
        start = (corner - radius * d_in, speed * d_in, zero)
        end = (corner + radius * d_out, speed * d_out, zero)
        return ruckig_piece(start, end, self.limits, f"the blend at waypoint {w}")

    def _error(self, piece: JointPiece, w: int) -> float:
        """Largest of the distance from the polyline and the closest approach to the waypoint."""
        samples = piece_samples(piece, _DEVIATION_SAMPLE_PERIOD_S)
        deviation = float(polyline_deviation(samples, self.kept[w - 1: w + 2]).max())
        miss = float(np.linalg.norm(samples - self.kept[w], axis=1).min())
        return max(deviation, miss)

    def trajectory(self) -> JointTrajectory:
        pieces: list[Piece] = []
        waypoint_times = [0.0]
        elapsed = 0.0
        for w in range(len(self.lengths)):
            start_q = self.kept[w] + self.radii[w] * self.units[w]
            end_q = self.kept[w + 1] - self.radii[w + 1] * self.units[w]
            line = line_piece(start_q, end_q, self.limits.velocity, self.limits.acceleration, self.limits.jerk,
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

    def _closest_time(self, piece: JointPiece, w: int) -> float:
        times = np.linspace(0.0, piece.duration_s, 64)
        distances = [np.linalg.norm(piece.at(float(t))[0] - self.kept[w]) for t in times]
        return float(times[int(np.argmin(distances))])
