"""A trajectory sampled on a setpoint stream's time grid: what the streaming loop plays row by row."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from robonav.pipeline.trajectory.trajectory import JointTrajectory
from robonav.pipeline.types import FloatArray


@dataclass(frozen=True)
class SetpointTable:
    """One trajectory sampled on the stream's grid: row k is the setpoint for `start_s + k * period`."""

    trajectory_id: str
    start_s: float
    """time.monotonic() of row 0, on the stream's grid [s]."""
    position: FloatArray
    """(K, n) [rad]; the last row is the rest state at the trajectory's end."""
    velocity: FloatArray
    """(K, n) [rad/s]"""
    acceleration: FloatArray
    """(K, n) [rad/s^2]"""
    complete: bool = True
    """False for a head: the whole table (same id and start) follows, and the head's last row is
    not the end of the motion."""


def sample_table(trajectory: JointTrajectory, trajectory_id: str, start_s: float, period_s: float,
                 max_rows: int | None = None) -> SetpointTable:
    """`trajectory` started at `start_s`, sampled every `period_s`; the last row is its end at rest.
    With `max_rows`, only the head of that many rows when the trajectory is longer."""
    rows = int(math.ceil(trajectory.duration_s / period_s - 1e-9)) + 1
    complete = max_rows is None or rows <= max_rows
    rows = rows if complete else max_rows
    q, qd, qdd = trajectory.sample_many(np.arange(rows) * period_s)  # clamped: the last row is the end
    return SetpointTable(trajectory_id, start_s, q, qd, qdd, complete)
