"""Precomputed lower bounds on the sphere gap of self-collision pairs that few joints separate.

A link pair whose links are separated by at most three revolute joints (the Panda's forearm
against its wrist, flange and hand; its upper arm against its forearm) has a relative pose
that depends on those joints alone, so the smallest gap between the two links' spheres is a
function of up to three angles. It is tabulated over the first two on a grid at construction;
a third joint is swept (the lower link's spheres become the circles they turn on, so the
table holds for any angle of it). At a state the table at the nearest grid point, minus how
far the spheres can move over half a grid step, bounds the gap from below. Where that bound
clears the contact tolerance the pair's sphere-against-sphere test cannot flag and is skipped,
so the broad phase answers exactly as without the table. On MotionBenchMaker edges in an empty
scene the self pairs were half of the per-state time, and these four pairs most of that; with
the tables a state costs about a fifth less. Where the spheres prove little, `piece_gaps`
raises the bounds to the links' convex pieces' distances (then a skipped pair is one FCL would
find apart, as with the separating planes).

How far a sphere moves: turning joint i by d rad moves every point downstream by at most
d * (its distance from joint i's origin), and that distance is at most the sum of the chain's
placement offsets below joint i plus the point's distance from the last joint's origin.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from robonav.pipeline.robot.lane_kinematics import REVOLUTE, LinkKinematics
from robonav.pipeline.types import FloatArray, IntArray

MAX_CHAIN_JOINTS = 3
"""Pairs separated by more joints get no table. Grids cover two joints; a third is swept (a 3-D
grid fine enough would cost seconds to build)."""

GRID_STEP_RAD = 0.02
"""Grid spacing aimed at (a Panda wrist pair then moves its spheres by up to ~6 mm in a half step)."""

MAX_CELLS_PER_JOINT = 256

ROUNDING_GUARD_M = 1e-6
"""Kept between a bound and the contact tolerance: the compiled kinematics round differently."""


@dataclass(frozen=True)
class SelfPairTables:
    """Gap bounds for the pairs of a self-pair list, as flat arrays for compiled code.

    Attributes:
        offset: (P,) start of pair p's table in `gap_m`, -1 when it has none.
        slot: (P, 2) q index of each grid axis, -1 for an unused axis (its count is 1).
        low: (P, 2) angle of grid index 0 [rad].
        step: (P, 2) grid spacing [rad].
        count: (P, 2) grid points per axis.
        gap_m: lower bounds on the smallest sphere gap (center distance minus both radii) for
            states nearest to each grid point, row-major over the two axes [m].
    """

    offset: IntArray
    slot: IntArray
    low: FloatArray
    step: FloatArray
    count: IntArray
    gap_m: FloatArray


def build_self_pair_tables(kin: LinkKinematics, lower_rad: FloatArray, upper_rad: FloatArray,
                           centers_joint: FloatArray, radii_m: FloatArray, link_start: IntArray,
                           self_pairs: IntArray) -> SelfPairTables:
    """Tables for every pair of `self_pairs` (P, 2) of collision links that at most
    `MAX_CHAIN_JOINTS` revolute joints separate, one link below the other.

    Args:
        kin: The robot's compiled kinematics.
        lower_rad, upper_rad: (dof,) joint limits; the grids span them.
        centers_joint: (S, 3) sphere centers in their link's joint frame [m].
        radii_m: (S,) sphere radii (the unpadded self-collision ones) [m].
        link_start: (L + 1,) spheres of link l are link_start[l]:link_start[l + 1].
    """
    n_pairs = self_pairs.shape[0]
    offset = np.full(n_pairs, -1, dtype=np.int64)
    slot = np.full((n_pairs, 2), -1, dtype=np.int64)
    low, step = np.zeros((n_pairs, 2)), np.ones((n_pairs, 2))
    count = np.ones((n_pairs, 2), dtype=np.int64)
    tables: list[FloatArray] = []
    filled = 0
    for p, (la, lb) in enumerate(self_pairs):
        chain = chain_joints(kin, int(kin.link_joint[la]), int(kin.link_joint[lb]))
        if chain is None:
            chain = chain_joints(kin, int(kin.link_joint[lb]), int(kin.link_joint[la]))
            la, lb = lb, la
        if chain is None or len(chain) > MAX_CHAIN_JOINTS or any(kin.joint_type[j] != REVOLUTE for j in chain):
            continue
        upper, lower = slice(link_start[la], link_start[la + 1]), slice(link_start[lb], link_start[lb + 1])
        if upper.start == upper.stop or lower.start == lower.stop:
            continue
        grids = []
        for d, j in enumerate(chain[:2]):
            s = int(kin.q_slot[j])
            lo, hi = float(lower_rad[s]), float(upper_rad[s])
            n = min(MAX_CELLS_PER_JOINT, max(2, math.ceil((hi - lo) / GRID_STEP_RAD) + 1))
            slot[p, d], low[p, d], step[p, d], count[p, d] = s, lo, (hi - lo) / (n - 1), n
            grids.append(lo + step[p, d] * np.arange(n))
        table = _grid_gaps(kin, chain, grids, centers_joint[upper], centers_joint[lower],
                           radii_m[upper, None] + radii_m[None, lower])
        # How far lb's spheres can move from the grid point to any state that rounds to it.
        reach_b = float(np.linalg.norm(centers_joint[lower], axis=1).max())
        margin = 0.0
        for d, j in enumerate(chain[:2]):
            below = sum(float(np.linalg.norm(kin.parent_from_joint_translation_m[k])) for k in chain[d + 1:])
            margin += (below + reach_b) * (0.5 * step[p, d] + 1e-9)
        offset[p] = filled
        tables.append(table - margin)
        filled += table.shape[0]
    gap_m = np.concatenate(tables) if tables else np.zeros(0)
    return SelfPairTables(offset, slot, low, step, count, np.ascontiguousarray(gap_m))


def _grid_gaps(kin: LinkKinematics, chain: list[int], grids: list[FloatArray], a: FloatArray, b: FloatArray,
               radii_sum: FloatArray) -> FloatArray:
    """Smallest gap between spheres `a` (Sa, 3) of the frame above the chain and `b` (Sb, 3) of its
    last joint's frame, at each grid point of the first two chain joints (G,) [m]. A third
    joint is swept: each b sphere becomes the circle it turns on, so the gap holds for any angle
    of that joint."""
    if len(chain) < 3:
        centers = points_in_upper_frame(kin, chain, grids, b)  # (G, Sb, 3)
        normals, circle_radii = None, None
    else:
        swept = chain[2]
        axis = kin.joint_axis[swept]
        height = b @ axis
        circle_radii = np.linalg.norm(b - height[:, None] * axis, axis=1)
        # Centers on the axis (where the joint's rotation leaves them), one frame up.
        above = kin.parent_from_joint_rotation[swept]
        centers = points_in_upper_frame(kin, chain[:2], grids,
                                         (height[:, None] * axis) @ above.T + kin.parent_from_joint_translation_m[swept])
        normals = points_in_upper_frame(kin, chain[:2], grids, (above @ axis)[None], rotate_only=True)  # (G, 1, 3)
    # |a - c|^2 = |a|^2 + |c|^2 - 2 a.c: matrix products instead of a (G, Sa, Sb, 3) difference
    # array (rounding ~1e-16 m^2, i.e. ~1e-8 m near contact, far inside ROUNDING_GUARD_M).
    a_sq, c_sq = np.einsum("ai,ai->a", a, a), np.einsum("gsi,gsi->gs", centers, centers)
    table = np.empty(centers.shape[0])
    for start in range(0, centers.shape[0], 4096):
        rows = slice(start, start + 4096)
        c = centers[rows]
        squared = a_sq[None, :, None] + c_sq[rows, None, :] - 2.0 * (c @ a.T).transpose(0, 2, 1)
        if normals is None:
            distance = np.sqrt(np.maximum(squared, 0.0))
        else:  # point to circle: out of its plane, and from its rim within the plane
            n = normals[rows, 0]
            out_of_plane = (n @ a.T)[:, :, None] - np.einsum("gsi,gi->gs", c, n)[:, None, :]
            in_plane = np.sqrt(np.maximum(squared - out_of_plane ** 2, 0.0))
            distance = np.sqrt(out_of_plane ** 2 + (in_plane - circle_radii[None, None, :]) ** 2)
        gap = distance - radii_sum[None]
        table[rows] = gap.reshape(gap.shape[0], -1).min(axis=1)
    return table


def chain_joints(kin: LinkKinematics, upper: int, lower: int) -> list[int] | None:
    """Joints from below `upper` down to `lower` (inclusive), top first; None when `lower` does
    not hang below (or at) `upper`."""
    chain = []
    j = lower
    while j != upper:
        if j == 0:
            return None
        chain.append(j)
        j = int(kin.parent[j])
    return chain[::-1]


def points_in_upper_frame(kin: LinkKinematics, chain: list[int], grids: list[FloatArray],
                           points: FloatArray, *, rotate_only: bool = False) -> FloatArray:
    """`points` (S, 3) of the chain's last joint frame, in the frame above the chain, at every
    combination of the grid angles (row-major): (G, S, 3). `rotate_only` for directions."""
    out = np.broadcast_to(points, (1, *points.shape)).copy()
    # Innermost joint first: p_above = placement @ (rotation(angle) @ p).
    for d in range(len(chain) - 1, -1, -1):
        j = chain[d]
        rotations = _axis_rotations(kin.joint_axis[j], grids[d])  # (N, 3, 3)
        moved = out[None] @ rotations.transpose(0, 2, 1)[:, None]  # (N, G, S, 3)
        moved = moved @ kin.parent_from_joint_rotation[j].T
        if not rotate_only:
            moved = moved + kin.parent_from_joint_translation_m[j]
        out = moved.reshape(-1, points.shape[0], 3)  # index n (this joint) is the outer one
    return out


def _axis_rotations(axis: FloatArray, angles: FloatArray) -> FloatArray:
    """Rotations about the unit `axis` by each of `angles`, (N, 3, 3) (Rodrigues)."""
    x, y, z = axis
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    s, c = np.sin(angles)[:, None, None], np.cos(angles)[:, None, None]
    return np.eye(3)[None] + s * k[None] + (1.0 - c) * (k @ k)[None]


def axis_grids(tables: SelfPairTables, dof: int) -> tuple[FloatArray, FloatArray, IntArray, IntArray]:
    """The tables' grids per joint value, for compiled code: (low, step, count), each (dof + 1,),
    and axis (P, 2): pair p's grid axis d reads joint value axis[p, d]. Row `dof` is the unused
    axis (count 1, always index 0); a joint value no table reads has count 0.

    Every table over a joint value shares one grid (it spans that joint's limits), so a state's
    grid indices are worked out once per state, not once per pair: that rounding, repeated for
    each of the UR5's 21 tabled pairs, was most of their cost.

    Raises:
        ValueError: two tables over one joint value have different grids.
    """
    low, step, count = np.zeros(dof + 1), np.ones(dof + 1), np.zeros(dof + 1, dtype=np.int64)
    count[dof] = 1
    for p, d in zip(*np.nonzero(tables.slot >= 0), strict=True):
        s = int(tables.slot[p, d])
        grid = (float(tables.low[p, d]), float(tables.step[p, d]), int(tables.count[p, d]))
        if count[s] and (low[s], step[s], count[s]) != grid:
            raise ValueError(f"self-pair tables over joint value {s} differ in their grids")
        low[s], step[s], count[s] = grid
    axis = np.where(tables.slot >= 0, tables.slot, dof).astype(np.int64)
    return low, step, count, axis


def no_pair_tables(n_pairs: int) -> SelfPairTables:
    """Tables that prove nothing for any of `n_pairs` pairs (every pair goes to its spheres)."""
    return SelfPairTables(np.full(n_pairs, -1, dtype=np.int64), np.full((n_pairs, 2), -1, dtype=np.int64),
                          np.zeros((n_pairs, 2)), np.ones((n_pairs, 2)), np.ones((n_pairs, 2), dtype=np.int64),
                          np.zeros(0))
