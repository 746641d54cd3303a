"""Input checks every joint-space planner shares: joint vectors and joint bounds."""

from __future__ import annotations

import numpy as np

from robonav.pipeline.types import FloatArray


def joint_vector(value: FloatArray, label: str, n: int | None = None) -> FloatArray:
    """`value` as a finite (n,) float array, or ValueError naming `label` and the bad index."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != 1 or arr.shape[0] == 0 or (n is not None and arr.shape[0] != n):
        expected = f"({n},)" if n is not None else "(n >= 1,)"
        raise ValueError(f"{label} must have shape {expected}, got shape {arr.shape}")
    bad = np.flatnonzero(~np.isfinite(arr))
    if bad.size:
        raise ValueError(f"{label}[{int(bad[0])}] must be finite, got {arr[bad[0]]}")
    return arr


def bounds_violation(q: FloatArray, lower: FloatArray, upper: FloatArray) -> str:
    """A sentence naming the first joint of `q` outside [lower, upper], or "" when inside."""
    for i in range(q.shape[0]):
        if q[i] < lower[i]:
            return f"joint {i} = {q[i]:.6g} is below its lower bound {lower[i]:.6g}"
        if q[i] > upper[i]:
            return f"joint {i} = {q[i]:.6g} is above its upper bound {upper[i]:.6g}"
    return ""
