"""Raise the self-pair tables' gap bounds where the links' convex pieces are apart.

Spheres cannot hug flat or boxy links. Two links that sit a few millimetres apart in every
state (the UR5's base plate under its upper arm's shoulder housing, its wrist 2 beside the
force-torque sensor) keep overlapping spheres everywhere: their sphere gap table proves
nothing, and every state ran the pair's separating planes (`separating_planes`), which on the
UR5 cost as much as the rest of a state's check. Where the pair's relative pose depends on at
most two joints, the distance between the links' convex pieces (the ones the planes use: they
hold every triangle of the meshes) is tabulated on the same grid: FCL's GJK distance at each
grid point whose sphere bound proves nothing, minus how far the lower link's pieces can move in
half a grid step. Where that bound clears the contact tolerance, the pieces, and so the meshes
FCL decides on, are apart at every state that rounds to that grid point: the pair is skipped
as it would be when its planes separate it, one table lookup instead of the planes.

A pair of three joints keeps its sphere bound alone: the swept third joint would need the
pieces' swept volumes.

The raised tables are built once per robot, spheres and pair list (`cached_pair_tables`).
"""

from __future__ import annotations

import dataclasses
import weakref
from collections.abc import Sequence

import fcl
import numpy as np
from scipy.spatial import ConvexHull

from robonav.pipeline.collision.fcl_shapes import convex_shape
from robonav.pipeline.collision.spheres.self_pair_tables import (
    ROUNDING_GUARD_M,
    SelfPairTables,
    build_self_pair_tables,
    chain_joints,
    points_in_upper_frame,
)
from robonav.pipeline.collision.spheres.separating_planes import joint_frame_pieces, shape_key
from robonav.pipeline.collision.spheres.table_store import dataclass_from_arrays, dataclass_to_arrays, stored, table_key
from robonav.pipeline.robot.lane_kinematics import LinkKinematics
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.types import FloatArray, IntArray

MAX_PIECE_CHAIN_JOINTS = 2
"""Pairs whose relative pose depends on more joints keep their sphere bound alone."""

HOT_SHARE = 0.5
"""Raise a pair's table only when its sphere bound proves nothing at this share of grid points."""

COARSE = 3
"""Grid points per axis one coarse point stands for: it is asked first with the margin of the
3 x 3 block around it, and only the blocks it leaves unproven are asked point by point."""

DISTANCE_GUARD_M = 1e-5
"""Taken off every distance GJK reports (its tolerance is about 1e-6 m)."""

_UNIT_FRAME = np.vstack([np.zeros(3), np.eye(3)])

Piece = tuple[fcl.CollisionObject, FloatArray, float]
"""A convex piece: its FCL object, bounding sphere center (3,) and radius [m]."""


def raise_by_piece_gaps(tables: SelfPairTables, kin: LinkKinematics, self_pairs: IntArray,
                        pieces_joint: Sequence[Sequence[FloatArray]], contact_m: float) -> SelfPairTables:
    """`tables` with each gap bound raised to the pieces' distance bound where that is larger.

    Only pairs whose sphere bound proves nothing at `HOT_SHARE` of their grid points are raised:
    elsewhere the planes run seldom, and each grid point asked costs a few GJK calls.

    How far a piece moves: as for the spheres (`self_pair_tables`), turning chain joint d by
    half a grid step moves a point of the lower link by at most that angle times (the chain's
    offsets below joint d + the point's distance from the last joint's origin); each piece
    takes its own farthest vertex, so the pieces near a joint keep a small margin.

    Args:
        tables: Sphere gap bounds of `self_pairs` (`build_self_pair_tables`).
        kin: The robot's compiled kinematics.
        self_pairs: (P, 2) collision link indices, as the tables were built for.
        pieces_joint: Per collision link, vertex sets (N, 3) in its joint's frame whose convex
            hulls hold all of the link's collision geometry.
        contact_m: The broad phase's contact tolerance: grid points whose bound already clears
            it are left as they are.
    """
    gap = tables.gap_m.copy()
    proven = contact_m + ROUNDING_GUARD_M + DISTANCE_GUARD_M
    for p, (la, lb) in enumerate(self_pairs):
        if tables.offset[p] < 0:
            continue
        chain = chain_joints(kin, int(kin.link_joint[la]), int(kin.link_joint[lb]))
        upper, lower = int(la), int(lb)
        if chain is None:
            chain = chain_joints(kin, int(kin.link_joint[lb]), int(kin.link_joint[la]))
            upper, lower = lower, upper
        if chain is None or len(chain) > MAX_PIECE_CHAIN_JOINTS or not pieces_joint[upper] or not pieces_joint[lower]:
            continue
        counts = [int(c) for c in tables.count[p, :len(chain)]]
        first, n_cells = int(tables.offset[p]), int(np.prod(tables.count[p]))
        table = gap[first:first + n_cells]  # a view: written in place
        todo = table <= proven
        if todo.sum() < HOT_SHARE * n_cells:
            continue
        # rate[d, j]: how far piece j of the lower link can move per radian of chain joint d.
        reach = np.array([float(np.linalg.norm(v, axis=1).max()) for v in pieces_joint[lower]])
        rate = np.array([[sum(float(np.linalg.norm(kin.parent_from_joint_translation_m[k])) for k in chain[d + 1:])]
                         for d in range(len(chain))]).reshape(-1, 1) + reach[None]
        slack = _PairSlack([_piece(v) for v in pieces_joint[upper]], [_piece(v) for v in pieces_joint[lower]], proven)

        def angles(index: FloatArray, d: int, p: int = p) -> FloatArray:
            return tables.low[p, d] + tables.step[p, d] * index

        steps = tables.step[p, :len(chain)]
        # Coarse: the block of COARSE^D grid points around each coarse point.
        coarse_index = [COARSE * np.arange(-(-c // COARSE)) + COARSE // 2 for c in counts]
        frames = points_in_upper_frame(kin, chain, [angles(i, d) for d, i in enumerate(coarse_index)], _UNIT_FRAME)
        margins = (rate * (0.5 * COARSE * steps[:, None] + 1e-9)).sum(axis=0)
        coarse = slack(frames, margins).reshape([len(i) for i in coarse_index])
        for d, c in enumerate(counts):
            coarse = np.repeat(coarse, COARSE, axis=d).take(np.arange(c), axis=d)
        coarse = coarse.reshape(-1)
        np.maximum(table, coarse, out=table)
        # Fine: the points a block did not prove.
        left = np.flatnonzero(todo & (coarse <= proven))
        if left.size:
            frames = points_in_upper_frame(kin, chain, [angles(np.arange(c), d) for d, c in enumerate(counts)],
                                           _UNIT_FRAME)[left]
            margins = (rate * (0.5 * steps[:, None] + 1e-9)).sum(axis=0)
            table[left] = np.maximum(table[left], slack(frames, margins))
    return dataclasses.replace(tables, gap_m=np.ascontiguousarray(gap))


def _piece(vertices: FloatArray) -> Piece:
    hull = ConvexHull(vertices)
    points = vertices[hull.vertices]
    center = 0.5 * (points.min(axis=0) + points.max(axis=0))
    return (fcl.CollisionObject(convex_shape(vertices, hull.simplices), fcl.Transform()), center,
            float(np.linalg.norm(points - center, axis=1).max()))


class _PairSlack:
    """Lower bounds on a link pair's piece distances, less each lower piece's margin."""

    def __init__(self, upper: list[Piece], lower: list[Piece], proven_m: float) -> None:
        self._upper, self._lower, self._proven = upper, lower, proven_m
        self._request = fcl.DistanceRequest()

    def __call__(self, frames: FloatArray, margins_m: FloatArray) -> FloatArray:
        """Per pose (frames (T, 4, 3): the lower joint frame's origin and unit axes' tips in the
        upper frame), min over piece pairs (i, j) of distance(i, j) - margins_m[j] - the GJK
        guard [m]. Piece pairs whose bounding spheres alone show that above `proven_m` count
        with that bound, without FCL; the rest go to FCL, the nearest first, and a pose stops at
        the first pair below `proven_m` (it is not proven, whatever the rest)."""
        upper, lower, proven = self._upper, self._lower, self._proven
        translations = frames[:, 0]
        rotations = (frames[:, 1:] - frames[:, :1]).transpose(0, 2, 1)
        centers_a = np.array([c for _, c, _ in upper])
        radii_a = np.array([r for _, _, r in upper])
        centers_b = np.array([c for _, c, _ in lower])
        radii_b = np.array([r for _, _, r in lower])
        placed_b = np.einsum("tij,bj->tbi", rotations, centers_b) + translations[:, None]  # (T, B, 3)
        bounds = (np.linalg.norm(placed_b[:, None] - centers_a[None, :, None], axis=3) - radii_a[None, :, None]
                  - radii_b[None, None, :] - margins_m[None, None, :] - DISTANCE_GUARD_M)  # (T, A, B)
        out = bounds.reshape(len(bounds), -1).min(axis=1)
        for t in np.flatnonzero(out <= proven):
            found = np.inf
            for flat in np.argsort(bounds[t], axis=None):
                i, j = divmod(int(flat), len(lower))
                if bounds[t, i, j] > proven:
                    found = min(found, float(bounds[t, i, j]))
                    break  # sorted: every pair left is bounded at least as far
                obj_b = lower[j][0]
                obj_b.setRotation(rotations[t])
                obj_b.setTranslation(translations[t])
                distance = fcl.distance(upper[i][0], obj_b, self._request, fcl.DistanceResult())
                found = min(found, distance - margins_m[j] - DISTANCE_GUARD_M)
                if found <= proven:
                    break
            out[t] = found
        return out


_pair_tables_of: weakref.WeakKeyDictionary[RobotModel, dict[str, SelfPairTables]] = weakref.WeakKeyDictionary()


def cached_pair_tables(robot: RobotModel, kin: LinkKinematics, centers_joint: FloatArray, radii_m: FloatArray,
                       link_start: IntArray, self_pairs: IntArray, contact_m: float) -> SelfPairTables:
    """`build_self_pair_tables` raised by the pieces' distances (`raise_by_piece_gaps`), once per
    robot, spheres and pair list (~2 s for the Panda, and every planning world of a robot has the
    same), kept in the installed `TableStore` too."""
    shapes = [[shape_key(s) for s in robot.link_collision_shapes[link]] for link in robot.collision_link_names]
    key = table_key("pair-tables", kin, robot.lower_limits_rad, robot.upper_limits_rad, centers_joint, radii_m,
                    link_start, self_pairs, shapes)
    per_robot = _pair_tables_of.setdefault(robot, {})
    if key not in per_robot:
        def build() -> SelfPairTables:
            tables = build_self_pair_tables(kin, robot.lower_limits_rad, robot.upper_limits_rad, centers_joint, radii_m,
                                            link_start, self_pairs)
            return raise_by_piece_gaps(tables, kin, self_pairs, joint_frame_pieces(robot, kin), contact_m)

        per_robot[key] = stored(key, build, dataclass_to_arrays, dataclass_from_arrays(SelfPairTables))
    return per_robot[key]
