"""Joint-space path measures and densification."""

from __future__ import annotations

import math

import numpy as np

from robonav.pipeline.types import FloatArray


def as_path(path: FloatArray, label: str = "path") -> FloatArray:
    """`path` as a (K, n) float64 array with K >= 1 finite rows.

    Raises:
        ValueError: wrong shape or a non-finite entry (naming `label`, the row and the column).
    """
    arr = np.asarray(path, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ValueError(f"{label} must have shape (K >= 1, n >= 1), got shape {arr.shape}")
    bad = np.argwhere(~np.isfinite(arr))
    if bad.size:
        i, j = (int(v) for v in bad[0])
        raise ValueError(f"{label}[{i}, {j}] must be finite, got {arr[i, j]}")
    return arr


def path_length_rad(path: FloatArray) -> float:
    """Sum of the Euclidean joint-space lengths of the segments of `path` (K, n) [rad]."""
    arr = as_path(path)
    return float(np.sum(np.linalg.norm(np.diff(arr, axis=0), axis=1)))


def max_joint_step_rad(path: FloatArray) -> float:
    """Largest single-joint change between consecutive waypoints of `path` (K, n); 0 for K = 1 [rad]."""
    arr = as_path(path)
    return float(np.max(np.abs(np.diff(arr, axis=0)))) if arr.shape[0] > 1 else 0.0


def interpolate_path(path: FloatArray, max_step_rad: float) -> FloatArray:
    """Densify `path` (K, n) so no joint moves more than `max_step_rad` between rows.

    Every original waypoint is kept; each segment is split into equal steps.

    Returns:
        (M, n) waypoints, M >= K, first and last rows equal to those of `path` [rad].
    """
    arr = as_path(path)
    if not (math.isfinite(max_step_rad) and max_step_rad > 0):
        raise ValueError(f"max_step_rad must be finite and > 0, got {max_step_rad}")
    rows = [arr[:1]]
    for a, b in zip(arr[:-1], arr[1:]):
        steps = max(1, math.ceil(float(np.max(np.abs(b - a))) / max_step_rad - 1e-9))
        t = np.arange(1, steps + 1)[:, None] / steps
        rows.append(a + (b - a) * t)
    out = np.vstack(rows)
    out[-1] = arr[-1]  # exact goal, free of interpolation round-off
    return out
