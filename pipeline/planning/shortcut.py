"""Random shortcutting of a joint-space path, then removal of redundant waypoints."""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable

import numpy as np

from robonav.pipeline.planning.metrics import as_path
from robonav.pipeline.transforms import FloatArray

_EPS = 1e-9


def shortcut_path(
    path: FloatArray,
    *,
    motion_valid: Callable[[FloatArray, FloatArray], bool],
    rng: np.random.Generator,
    iterations: int,
    patience: int = 0,
) -> FloatArray:
    """Shorten `path` by straight connections that pass `motion_valid`.

    A first pass drops waypoints whose neighbours connect directly (cheap, and most of the gain
    on a raw RRT path: on MotionBenchMaker it halves the edge checks for the same length). Each
    iteration then draws two arc-length positions on the path (anywhere, also mid-segment) and
    replaces the stretch between them by a straight segment when that is shorter and valid.
    A final pass drops waypoints again. Every segment of the output was accepted by
    `motion_valid` or is a piece of an input segment. Pieces are not checked again (as in OMPL's
    and MoveIt's shortcutting): under a continuous check that changes nothing, and a discretised
    check samples a piece at other states than the whole, so a caller that needs every output
    segment to pass its own discretised check re-validates the result (`MotionPlanner` does). On
    MotionBenchMaker the pieces were a third of the shortcut's checked states.

    Args:
        path: (K, n) waypoints [rad], assumed valid segment by segment.
        motion_valid: Validity of the straight segment between two (n,) states.
        rng: Source of the random positions; the same seed gives the same result.
        iterations: Number of shortcut attempts (>= 0).
        patience: Stop after this many attempts in a row that changed nothing (0: never). On
            MotionBenchMaker 10 saves a third of the edge checks for paths 0.2 % longer (median).

    Returns:
        (K', n) path with the same first and last rows, never longer (Euclidean joint-space
        length) than `path`.
    """
    arr = as_path(path).copy()
    if iterations < 0:
        raise ValueError(f"iterations must be >= 0, got {iterations}")
    if patience < 0:
        raise ValueError(f"patience must be >= 0, got {patience}")
    arr = _drop_redundant(arr, motion_valid)
    # The random positions come in one draw, as fractions of the path length: per attempt, a
    # Generator call and numpy's reductions on a few 7-vectors cost more than the arithmetic
    # (on MotionBenchMaker this bookkeeping was a third of the shortcut's time).
    fractions = rng.uniform(0.0, 1.0, size=(iterations, 2))
    cumulative = _cumulative_lengths(arr)
    unchanged = 0
    for attempt in range(iterations):
        if arr.shape[0] < 3:
            break
        shorter = _try_shortcut(arr, cumulative, motion_valid, fractions[attempt])
        if shorter is arr:
            unchanged += 1
        else:
            unchanged = 0
            arr, cumulative = shorter, _cumulative_lengths(shorter)
        if patience and unchanged >= patience:
            break
    return _drop_redundant(arr, motion_valid)


def _cumulative_lengths(arr: FloatArray) -> list[float]:
    """Arc length at each waypoint of `arr` (K, n), from 0 [rad]."""
    steps = np.diff(arr, axis=0)
    return [0.0, *np.cumsum(np.sqrt(np.einsum("ij,ij->i", steps, steps))).tolist()]


def _distance(a: FloatArray, b: FloatArray) -> float:
    d = b - a
    return math.sqrt(d.dot(d))


def _try_shortcut(arr: FloatArray, cumulative: list[float], motion_valid: Callable[[FloatArray, FloatArray], bool],
                  fractions: FloatArray) -> FloatArray:
    total = cumulative[-1]
    if total <= _EPS:
        return arr
    s1, s2 = sorted((total * float(fractions[0]), total * float(fractions[1])))
    last = len(cumulative) - 2
    i1 = min(bisect.bisect_right(cumulative, s1) - 1, last)
    i2 = min(bisect.bisect_right(cumulative, s2) - 1, last)
    if i1 == i2:
        return arr  # both on one straight segment: nothing to gain
    p1 = _point_on_segment(arr, cumulative, i1, s1)
    p2 = _point_on_segment(arr, cumulative, i2, s2)
    if _distance(p1, p2) >= (s2 - s1) - _EPS:
        return arr
    if not motion_valid(p1, p2):
        return arr
    head = [arr[: i1 + 1]]
    if _distance(arr[i1], p1) > _EPS:
        head.append(p1[None])
    tail = [arr[i2 + 1:]]
    if _distance(p2, arr[i2 + 1]) > _EPS:
        tail.insert(0, p2[None])
    return np.vstack(head + tail)


def _point_on_segment(arr: FloatArray, cumulative: list[float], i: int, s: float) -> FloatArray:
    length = cumulative[i + 1] - cumulative[i]
    if length <= _EPS:
        return arr[i].copy()
    t = min(max((s - cumulative[i]) / length, 0.0), 1.0)
    return arr[i] + (arr[i + 1] - arr[i]) * t


def _drop_redundant(arr: FloatArray, motion_valid: Callable[[FloatArray, FloatArray], bool]) -> FloatArray:
    """Greedy pass: skip a waypoint when the last kept one connects straight to the next one."""
    keep = [0]
    for i in range(1, arr.shape[0] - 1):
        if _distance(arr[keep[-1]], arr[i]) <= _EPS:
            continue  # duplicate waypoint
        if not motion_valid(arr[keep[-1]], arr[i + 1]):
            keep.append(i)
    if arr.shape[0] > 1:
        keep.append(arr.shape[0] - 1)
    return arr[keep].copy()
