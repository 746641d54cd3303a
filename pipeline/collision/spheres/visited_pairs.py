"""Which self pairs the lane check visits, and in what order.

Not the pairs a gap table proves apart at every state (`self_pair_tables`): a gripper's parts
rigid on one wrist never move apart or together. The rest in groups that share their first link
and the joint frame of their second, so that one test of bounding spheres may skip a link
against a whole rigid body (`lanes.lanes_suspect`). Either way the answers are those of every
pair visited on its own.
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from robonav.pipeline.collision.spheres.self_pair_tables import ROUNDING_GUARD_M, SelfPairTables
from robonav.pipeline.types import BoolArray, FloatArray, IntArray


def pairs_apart_everywhere(tables: SelfPairTables, lower_rad: FloatArray, upper_rad: FloatArray,
                           contact_eps_m: float) -> BoolArray:
    """(P,) whether pair p's table proves it apart at every state, also one outside the limits:
    it clears `contact_eps_m` at every grid point (as the compiled check asks), and each grid
    axis spans a whole turn of its (revolute) joint, or there is none (a pair no joint of the
    group moves apart, such as a gripper's fingers and a sensor flange on one wrist).

    Such a pair needs no check at all: on the UR5 with its gripper, eight pairs whose spheres are
    always near each other, each costing a table look-up per state."""
    apart = np.zeros(tables.offset.shape[0], dtype=np.bool_)
    for p, start in enumerate(tables.offset):
        if start < 0:
            continue
        gaps = tables.gap_m[start:start + int(np.prod(tables.count[p]))]
        whole_turns = all(s < 0 or upper_rad[s] - lower_rad[s] >= 2.0 * math.pi for s in tables.slot[p])
        apart[p] = whole_turns and bool(np.all(gaps > contact_eps_m + ROUNDING_GUARD_M))
    return apart


def pair_groups(self_pairs: IntArray, checked: IntArray, link_joint: IntArray, bound_center_joint: FloatArray,
                bound_self: FloatArray) -> tuple[IntArray, IntArray, FloatArray, FloatArray]:
    """The self pairs `checked` (indices into `self_pairs` (P, 2)) in groups that share their
    first link and the joint frame of their second: (order (C,), group_end (C,), center (C, 3),
    radius (C,)). Position i of `order` starting a group of several pairs holds the group's end
    position and a sphere (its center in the second links' joint frame) around their bounding
    spheres; elsewhere the radius is -1. One test of the first link's bounding sphere against a
    group's skips all of its pairs: the UR5's base, shoulder and upper arm against the dozen
    links rigid on its last wrist joint cost a bounding-sphere test each per state otherwise."""
    def key(p: int) -> tuple[int, int]:
        return int(self_pairs[p, 0]), int(link_joint[self_pairs[p, 1]])

    order = np.array(sorted(np.asarray(checked, dtype=np.int64), key=key), dtype=np.int64)
    group_end = np.zeros(len(order), dtype=np.int64)
    center, radius = np.zeros((len(order), 3)), np.full(len(order), -1.0)
    first = 0
    for _, members in itertools.groupby(order, key=key):
        end = first + len(list(members))
        group_end[first] = end
        if end - first > 1:
            links = self_pairs[order[first:end], 1]
            points = bound_center_joint[links]
            center[first] = 0.5 * (points.min(axis=0) + points.max(axis=0))
            radius[first] = float(np.max(np.linalg.norm(points - center[first], axis=1) + bound_self[links]))
        first = end
    return order, group_end, center, radius
