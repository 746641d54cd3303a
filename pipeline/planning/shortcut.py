"""Random shortcutting of a joint-space path, then removal of redundant waypoints."""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from robonav.pipeline.planning.metrics import as_path
from robonav.pipeline.types import FloatArray, MotionValidFn

_EPS = 1e-9


def shortcut_path(
    path: FloatArray,
    *,
    motion_valid: MotionValidFn,
    rng: np.random.Generator,
    iterations: int,
    patience: int = 0,
) -> FloatArray:
    """Shorten `path` by straight connections that pass `motion_valid`.

    A first pass drops waypoints a kept one connects past directly (cheap, and most of the gain
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
    # The random positions come in one draw, as fractions of the path length, and the
    # bookkeeping between motion checks (arc lengths, positions, whether a connection is
    # shorter, the splice) is compiled: on MotionBenchMaker it was a fifth of the plan's time
    # in Python, more than the edge checks of the shortcut's valid connections.
    fractions = rng.uniform(0.0, 1.0, size=(iterations, 2))
    cumulative = _cumulative_lengths(arr)
    p1, p2 = np.empty(arr.shape[1]), np.empty(arr.shape[1])
    attempt, unchanged = 0, 0
    while True:
        attempt, unchanged, i1, i2 = _next_candidate(arr, cumulative, fractions, attempt, unchanged, patience, p1, p2)
        if attempt >= iterations:
            break
        if motion_valid(p1.copy(), p2.copy()):
            arr = _splice(arr, i1, i2, p1, p2)
            cumulative = _cumulative_lengths(arr)
            unchanged = 0
        else:
            unchanged += 1
            if patience and unchanged >= patience:
                break
        attempt += 1
    return _drop_redundant(arr, motion_valid)


@nb.njit(cache=True)
def _cumulative_lengths(arr: FloatArray) -> FloatArray:
    """Arc length at each waypoint of `arr` (K, n), from 0 [rad]."""
    cumulative = np.zeros(arr.shape[0])
    for i in range(1, arr.shape[0]):
        cumulative[i] = cumulative[i - 1] + _distance(arr[i - 1], arr[i])
    return cumulative


@nb.njit(cache=True)
def _distance(a: FloatArray, b: FloatArray) -> float:
    total = 0.0
    for j in range(a.shape[0]):
        total += (b[j] - a[j]) * (b[j] - a[j])
    return math.sqrt(total)


@nb.njit(cache=True)
def _next_candidate(arr: FloatArray, cumulative: FloatArray, fractions: FloatArray, attempt: int, unchanged: int,
                    patience: int, p1: FloatArray, p2: FloatArray) -> tuple[int, int, int, int]:
    """From `attempt` on, the first attempt whose two positions (written to `p1`, `p2`) connect
    straight in less than the path between them; attempts passed over count as unchanged.

    Returns:
        (attempt, unchanged, i1, i2): the positions lie on segments i1 < i2. attempt is
        len(fractions) when none is left: all drawn, patience run out, or fewer than 3 waypoints.
    """
    done = fractions.shape[0]
    total = cumulative[-1]
    last = arr.shape[0] - 2
    while attempt < done:
        if arr.shape[0] < 3:
            return done, unchanged, 0, 0
        if total > _EPS:
            s1 = min(total * fractions[attempt, 0], total * fractions[attempt, 1])
            s2 = max(total * fractions[attempt, 0], total * fractions[attempt, 1])
            i1 = min(np.searchsorted(cumulative, s1, side="right") - 1, last)
            i2 = min(np.searchsorted(cumulative, s2, side="right") - 1, last)
            if i1 != i2:  # else both on one straight segment: nothing to gain
                _point_on_segment(arr, cumulative, i1, s1, p1)
                _point_on_segment(arr, cumulative, i2, s2, p2)
                if _distance(p1, p2) < (s2 - s1) - _EPS:
                    return attempt, unchanged, i1, i2
        unchanged += 1
        if patience and unchanged >= patience:
            return done, unchanged, 0, 0
        attempt += 1
    return done, unchanged, 0, 0


@nb.njit(cache=True)
def _point_on_segment(arr: FloatArray, cumulative: FloatArray, i: int, s: float, out: FloatArray) -> None:
    length = cumulative[i + 1] - cumulative[i]
    t = 0.0 if length <= _EPS else min(max((s - cumulative[i]) / length, 0.0), 1.0)
    for j in range(arr.shape[1]):
        out[j] = arr[i, j] + (arr[i + 1, j] - arr[i, j]) * t


@nb.njit(cache=True)
def _splice(arr: FloatArray, i1: int, i2: int, p1: FloatArray, p2: FloatArray) -> FloatArray:
    """`arr` up to waypoint i1, then p1 and p2 (each unless it repeats its neighbour), then
    `arr` from waypoint i2 + 1."""
    with_p1 = _distance(arr[i1], p1) > _EPS
    with_p2 = _distance(p2, arr[i2 + 1]) > _EPS
    head, tail = i1 + 1, arr.shape[0] - (i2 + 1)
    out = np.empty((head + int(with_p1) + int(with_p2) + tail, arr.shape[1]))
    out[:head] = arr[:head]
    k = head
    if with_p1:
        out[k] = p1
        k += 1
    if with_p2:
        out[k] = p2
        k += 1
    out[k:] = arr[i2 + 1:]
    return out


def _drop_redundant(arr: FloatArray, motion_valid: MotionValidFn) -> FloatArray:
    """Greedy pass: from each kept waypoint, on to the farthest later one it connects to straight,
    found by galloping (the next, then 2, 4, 8 ... waypoints on) and bisecting the last gap.

    Trying every next waypoint in turn checked one free connection per dropped waypoint, each
    longer than the last, and a free connection costs all its states (a blocked one a few). On
    the same raw paths of MotionBenchMaker's UR5 problems, galloping took the whole shortcut
    about an eighth less time, for paths as long.
    Validity along a path is not monotone, so a waypoint past a blocked probe may be kept that
    a slower pass would drop; the random shortcuts and the final pass see it again."""
    last = arr.shape[0] - 1
    if last < 2:
        return arr.copy()
    # Duplicate waypoints first; the first and last rows stay, exactly.
    distinct = [0]
    for i in range(1, last):
        if _distance(arr[distinct[-1]], arr[i]) > _EPS:
            distinct.append(i)
    arr = arr[[*distinct, last]]
    last = arr.shape[0] - 1
    keep = [0]
    while keep[-1] < last:
        i = keep[-1]
        good, bad, step = i + 1, last + 1, 1  # the path's own segment from i is valid
        while good < last:
            probe = min(good + step, last)
            if not motion_valid(arr[i], arr[probe]):
                bad = probe
                break
            good, step = probe, step * 2
        while bad - good > 1:
            middle = (good + bad) // 2
            if motion_valid(arr[i], arr[middle]):
                good = middle
            else:
                bad = middle
        keep.append(good)
    return arr[keep].copy()
