"""Continuous joints: an angle and the angle a whole number of turns away are the same state.

A `continuous` URDF joint is planned linearly over a bounded range (`CONTINUOUS_JOINT_RANGE_RAD`,
two turns each way, or `position_limits_rad`), so paths, interpolation and the executor stay
linear in its angle. Wrap-around enters at the ends of a query: a goal angle is replaced by
its equivalent nearest the start within that range (the shortest turn), and "is the arm at its
goal" is asked modulo a turn.
"""

from __future__ import annotations

import math

import numpy as np

from robonav.pipeline.types import FloatArray

TURN_RAD = 2.0 * math.pi


def nearest_turn_rad(q_rad: FloatArray, reference_rad: FloatArray, lower_rad: FloatArray, upper_rad: FloatArray,
                     turning: np.ndarray) -> FloatArray:
    """`q_rad` (n,) or (G, n) with each `turning` joint moved by whole turns to the equivalent
    angle nearest `reference_rad` (n,) that lies within [`lower_rad`, `upper_rad`].

    The distance to the reference is convex in the number of turns k, so the best k in range
    is the unconstrained best clipped to the k that keep the angle in range. A joint with no
    equivalent in range (a range narrower than a turn) keeps its value, for the limit check to
    refuse. Other joints are returned as given.

    Args:
        turning: (n,) bool, True for the joints that wrap (continuous joints).
    """
    q = np.array(q_rad, dtype=np.float64)
    if not np.any(turning):
        return q
    # A small allowance so that a goal given exactly at a bound (e.g. 2*pi) keeps its own turn.
    k_low = np.ceil((lower_rad - q) / TURN_RAD - 1e-12)
    k_high = np.floor((upper_rad - q) / TURN_RAD + 1e-12)
    k = np.clip(np.round((reference_rad - q) / TURN_RAD), k_low, k_high)
    moved = np.where(turning & (k_low <= k_high), q + k * TURN_RAD, q)
    # An equivalent a hair outside a bound after round-off sits on the bound.
    return np.where(turning & (k_low <= k_high), np.clip(moved, lower_rad, upper_rad), moved)


def joint_distance_rad(a_rad: FloatArray, b_rad: FloatArray, turning: np.ndarray) -> FloatArray:
    """Per-joint distance |a - b| [rad, or m for prismatic joints], modulo a turn for `turning`
    joints (at most pi there): how far a continuous joint is from an angle, whichever turn it is on."""
    diff = np.abs(np.asarray(a_rad, dtype=np.float64) - np.asarray(b_rad, dtype=np.float64))
    wrapped = np.abs(np.mod(diff + math.pi, TURN_RAD) - math.pi)
    return np.where(turning, wrapped, diff)
