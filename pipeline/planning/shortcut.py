"""Random shortcutting of a joint-space path, then removal of redundant waypoints."""

from __future__ import annotations

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
    unchanged = 0
    for _ in range(iterations):
        if arr.shape[0] < 3:
            break
        shorter = _try_shortcut(arr, motion_valid, rng)
        unchanged = unchanged + 1 if shorter is arr else 0
        arr = shorter
        if patience and unchanged >= patience:
            break
    return _drop_redundant(arr, motion_valid)


def _try_shortcut(
    arr: FloatArray, motion_valid: Callable[[FloatArray, FloatArray], bool], rng: np.random.Generator
) -> FloatArray:
    seg_len = np.linalg.norm(np.diff(arr, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])
    total = cum[-1]
    if total <= _EPS:
        return arr
    s1, s2 = np.sort(rng.uniform(0.0, total, size=2))
    i1 = min(int(np.searchsorted(cum, s1, side="right")) - 1, len(seg_len) - 1)
    i2 = min(int(np.searchsorted(cum, s2, side="right")) - 1, len(seg_len) - 1)
    if i1 == i2:
        return arr  # both on one straight segment: nothing to gain
    p1 = _point_on_segment(arr, cum, seg_len, i1, s1)
    p2 = _point_on_segment(arr, cum, seg_len, i2, s2)
    if np.linalg.norm(p2 - p1) >= (s2 - s1) - _EPS:
        return arr
    if not motion_valid(p1, p2):
        return arr
    head = [arr[: i1 + 1]]
    if np.linalg.norm(p1 - arr[i1]) > _EPS:
        head.append(p1[None])
    tail = [arr[i2 + 1:]]
    if np.linalg.norm(arr[i2 + 1] - p2) > _EPS:
        tail.insert(0, p2[None])
    return np.vstack(head + tail)


def _point_on_segment(arr: FloatArray, cum: FloatArray, seg_len: FloatArray, i: int, s: float) -> FloatArray:
    if seg_len[i] <= _EPS:
        return arr[i].copy()
    t = min(max((s - cum[i]) / seg_len[i], 0.0), 1.0)
    return arr[i] + (arr[i + 1] - arr[i]) * t


def _drop_redundant(arr: FloatArray, motion_valid: Callable[[FloatArray, FloatArray], bool]) -> FloatArray:
    """Greedy pass: skip a waypoint when the last kept one connects straight to the next one."""
    keep = [0]
    for i in range(1, arr.shape[0] - 1):
        prev = arr[keep[-1]]
        if np.linalg.norm(arr[i] - prev) <= _EPS:
            continue  # duplicate waypoint
        if not motion_valid(prev, arr[i + 1]):
            keep.append(i)
    if arr.shape[0] > 1:
        keep.append(arr.shape[0] - 1)
    return arr[keep].copy()
