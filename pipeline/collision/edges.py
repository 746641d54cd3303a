"""How a straight joint-space edge is checked: its step count, and the order of its states."""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from robonav.pipeline.types import FloatArray


def step_count(a: FloatArray, b: FloatArray, resolution_rad: float) -> int:
    """Steps of a straight joint-space edge from `a` to `b` so no joint moves more than `resolution_rad` per step."""
    if not (math.isfinite(resolution_rad) and resolution_rad > 0):
        raise ValueError(f"resolution_rad must be finite and > 0, got {resolution_rad}")
    return max(1, math.ceil(float(np.max(np.abs(b - a))) / resolution_rad - 1e-9))


@lru_cache(maxsize=256)
def bisection_order(steps: int) -> tuple[int, ...]:
    """Interior indices 1..steps-1, midpoints of ever finer halvings first."""
    order, queue = [], [(0, steps)]
    while queue:
        next_queue = []
        for lo, hi in queue:
            if hi - lo < 2:
                continue
            mid = (lo + hi) // 2
            order.append(mid)
            next_queue += [(lo, mid), (mid, hi)]
        queue = next_queue
    return tuple(order)
