"""The sphere broad phase's per-state and per-edge checks, several states at a time (numba).

A state's check is the same as ever: forward kinematics, every link's spheres placed, each
sphere against the scene primitives, the occupied voxels, the self-collision pairs' spheres and
the attached spheres. Here up to `LANES` states go through it together, as the lanes of the
innermost array axis: forward kinematics, sphere placement and the sphere-primitive and
sphere-sphere distances are loops over lanes with no branch inside, which the compiler turns
into SIMD instructions (what VAMP does by hand in C++). Culling stays per link and pair, taken
when any lane needs the finer test; a lane's answer is the same whatever the other lanes hold.

Sphere centers are stored in their joint's frame (the link placement folded in), so the link
frames are never formed. The voxel and attached-sphere tests stay per lane: they are rare
(occupancy maps, grasped objects) and branchy.

An edge's states are checked in `CollisionWorld.motion_valid` order, `LANES` at a time
(`edge_lanes.py`); the first lanes of a blocked edge (its end, midpoint, quarter points...)
usually flag it at once. Each lane keeps its own clearance from the occupied voxels
(`lane_clearance`): near a query's start and goals it shrinks (`surface_allowance.py`).
"""

from __future__ import annotations

import math

import numba as nb
from numba.core import types
from numba.experimental import structref

from robonav.pipeline.collision.spheres.gjk import link_keeps_off_object
from robonav.pipeline.collision.spheres.kernels import (
    BOX,
    CONTACT_EPS_M,
    CYLINDER,
    SPHERE,
    object_distance,
    touches_cells,
    voxel_distance,
)
from robonav.pipeline.collision.spheres.self_pair_tables import ROUNDING_GUARD_M
from robonav.pipeline.collision.spheres.separating_planes import GUARD_M, link_outside_box, pair_separated
from robonav.pipeline.robot.lane_kinematics import forward_joints_lanes
from robonav.pipeline.types import BoolArray, FloatArray, IntArray

LANES = 16
"""States checked together (measured on MBM edges, per state: 4 lanes 0.87 us, 8 0.67, 16 0.59)."""

VECTOR = 4
"""float64 lanes in one AVX2 vector."""

LANE_WORLD_FIELDS: tuple[str, ...] = (
    # kinematics (`LinkKinematics.lane_arrays`)
    "parent", "joint_type", "q_slot", "coefficients", "base_joint", "joint_from_base",
    # spheres, in their joints' frames
    "centers_joint", "radii_self", "radii_world", "link_start", "bound_center_joint", "bound_self", "bound_world",
    "self_pairs", "link_joint", "joint_from_link_rotation", "joint_from_link_translation",
    # the self pairs checked, in groups one bounding-sphere test may skip (`broad_phase.pair_groups`)
    "pair_checked", "pair_group_end", "pair_group_center", "pair_group_radius",
    # gap bounds of self pairs few joints apart (`self_pair_tables`)
    "pair_offset", "pair_axis", "axis_low", "axis_step", "axis_count", "pair_count", "pair_gap",
    # planes that separate self pairs whose spheres overlap (`separating_planes`)
    "sep_pair_whole", "sep_pair_range", "sep_sub_piece", "sep_sub_start", "sep_side", "sep_plane", "sep_piece_link",
    "sep_piece_center", "sep_piece_radius", "sep_vertex_start", "sep_vertices", "sep_link_whole", "sep_link_growth",
    # scene primitives
    "obj_kind", "obj_rotation", "obj_translation", "obj_param", "obj_bound",
    # occupied voxels: distance field, the occupied cells (maybe on a finer grid) and the clearance kept from them
    "has_grid", "grid", "grid_origin", "grid_voxel", "grid_box", "occupied", "fine", "fine_origin", "fine_voxel",
    "fine_slot", "fine_box", "grid_column", "grid_clearance", "tier_clearance",
    # attached spheres
    "att_center_joint", "att_radius", "att_radius_world", "att_joint", "att_skip",
    # scratch: lane inputs and outputs, frames, placed spheres
    "cos_lanes", "sin_lanes", "q_lanes", "lane_clearance", "lane_tier", "flags", "frames", "sphere_lanes", "bound_lanes", "placed", "near",
    "distance", "att_lanes", "pair_near", "axis_cells", "near_spheres",
)
"""What the lane kernels read, as one object: a call from Python unboxes one reference (~0.6 us)
instead of some 45 arrays (~3 us, more than a 16-state chunk of an edge costs)."""


@structref.register
class LaneWorldType(types.StructRef):
    def preprocess_fields(self, fields):  # noqa: ANN001, ANN201 (numba's hook)
        return tuple((name, types.unliteral(kind)) for name, kind in fields)


class LaneWorld(structref.StructRefProxy):
    """The arrays of `LANE_WORLD_FIELDS`, by keyword, in one compiled-code object (rebuilt, never
    changed, when the scene changes; the scratch buffers are shared between rebuilds)."""

    def __new__(cls, **arrays: object):  # noqa: ANN204
        missing = set(LANE_WORLD_FIELDS) ^ set(arrays)
        if missing:
            raise ValueError(f"LaneWorld fields missing or unknown: {sorted(missing)}")
        # Built by a cached compiled function: StructRefProxy.__new__ compiles its constructor in
        # every new process (numba cannot cache it), 3-10 s of every planner and executor start.
        return _new_lane_world(tuple(arrays[name] for name in LANE_WORLD_FIELDS))


structref.define_constructor(LaneWorld, LaneWorldType, list(LANE_WORLD_FIELDS))
structref.define_boxing(LaneWorldType, LaneWorld)


@nb.njit(cache=True)
def _new_lane_world(fields):  # noqa: ANN001, ANN202 (a tuple of the LANE_WORLD_FIELDS arrays, in order)
    return LaneWorld(*fields)


# The helpers below are called, not inlined at numba IR level (`inline="always"`): inlining
# typed them again in every kernel, which made a cold `robonav up` miss its 60 s start; called,
# the Panda benchmark's median stayed within noise (4.8 ms against 4.7 ms).
@nb.njit(cache=True)
def object_distance_lanes(n: int, points: FloatArray, row: int, k: int, kind: IntArray, rotation: FloatArray,
                          translation: FloatArray, param: FloatArray, out: FloatArray) -> None:  # pragma: no cover (compiled)
    """out[w] = signed distance from points[row, :, w] to object k [m], for the n lanes."""
    ox, oy, oz = translation[k, 0], translation[k, 1], translation[k, 2]
    r00, r01, r02 = rotation[k, 0, 0], rotation[k, 0, 1], rotation[k, 0, 2]
    r10, r11, r12 = rotation[k, 1, 0], rotation[k, 1, 1], rotation[k, 1, 2]
    r20, r21, r22 = rotation[k, 2, 0], rotation[k, 2, 1], rotation[k, 2, 2]
    p0, p1, p2 = param[k, 0], param[k, 1], param[k, 2]
    shape = kind[k]
    # One loop per kind: a branch on the kind inside the lane loop would keep it scalar.
    if shape == BOX:
        for w in range(n):
            dx, dy, dz = points[row, 0, w] - ox, points[row, 1, w] - oy, points[row, 2, w] - oz
            qx = abs(r00 * dx + r10 * dy + r20 * dz) - p0
            qy = abs(r01 * dx + r11 * dy + r21 * dz) - p1
            qz = abs(r02 * dx + r12 * dy + r22 * dz) - p2
            ex, ey, ez = max(qx, 0.0), max(qy, 0.0), max(qz, 0.0)
            out[w] = math.sqrt(ex * ex + ey * ey + ez * ez) + min(max(qx, max(qy, qz)), 0.0)
    elif shape == SPHERE:
        for w in range(n):
            dx, dy, dz = points[row, 0, w] - ox, points[row, 1, w] - oy, points[row, 2, w] - oz
            out[w] = math.sqrt(dx * dx + dy * dy + dz * dz) - p0
    elif shape == CYLINDER:
        for w in range(n):
            dx, dy, dz = points[row, 0, w] - ox, points[row, 1, w] - oy, points[row, 2, w] - oz
            px = r00 * dx + r10 * dy + r20 * dz
            py = r01 * dx + r11 * dy + r21 * dz
            pz = r02 * dx + r12 * dy + r22 * dz
            radial = math.sqrt(px * px + py * py) - p0
            axial = abs(pz) - p1
            er, ea = max(radial, 0.0), max(axial, 0.0)
            out[w] = math.sqrt(er * er + ea * ea) + min(max(radial, axial), 0.0)
    else:  # capsule
        for w in range(n):
            dx, dy, dz = points[row, 0, w] - ox, points[row, 1, w] - oy, points[row, 2, w] - oz
            px = r00 * dx + r10 * dy + r20 * dz
            py = r01 * dx + r11 * dy + r21 * dz
            pz = r02 * dx + r12 * dy + r22 * dz
            ez = pz - min(max(pz, -p1), p1)
            out[w] = math.sqrt(px * px + py * py + ez * ez) - p0


@nb.njit(cache=True)
def _any_within(n: int, distance: FloatArray, limit: float) -> bool:  # pragma: no cover (compiled)
    hit = False
    for w in range(n):
        hit |= distance[w] <= limit
    return hit


@nb.njit(cache=True)
def _flag_within(n: int, distance: FloatArray, limit: float, flags: BoolArray) -> None:  # pragma: no cover (compiled)
    for w in range(n):
        flags[w] |= distance[w] <= limit


@nb.njit(cache=True)
def points_within(n: int, points_a: FloatArray, i: int, points_b: FloatArray, j: int, reach: float,
                  out: BoolArray) -> bool:  # pragma: no cover
    """out[w] = points_a[i, :, w] and points_b[j, :, w] are within `reach` (+ contact epsilon); any of them."""
    r = reach + CONTACT_EPS_M
    r2 = r * r
    hit = False
    for w in range(n):
        dx = points_a[i, 0, w] - points_b[j, 0, w]
        dy = points_a[i, 1, w] - points_b[j, 1, w]
        dz = points_a[i, 2, w] - points_b[j, 2, w]
        near = dx * dx + dy * dy + dz * dz <= r2
        out[w] = near
        hit |= near
    return hit


@nb.njit(cache=True)
def table_cells(n: int, q_lanes: FloatArray, low: FloatArray, step: FloatArray, count: IntArray,
                cells: IntArray) -> None:  # pragma: no cover (compiled)
    """cells[a, w] = the index of lane w's joint value a on the self-pair tables' grid of that
    value (`self_pair_tables.axis_grids`), -1 off the grid, for the values a table reads. Row
    `dof` (the unused axis) stays 0."""
    for a in range(count.shape[0] - 1):
        if count[a] == 0:
            continue
        lo, st, top = low[a], step[a], count[a]
        for w in range(n):
            i = int(math.floor((q_lanes[a, w] - lo) / st + 0.5))
            cells[a, w] = i if 0 <= i < top else -1


@nb.njit(cache=True)
def pair_clear(n: int, p: int, cells: IntArray, offset: IntArray, axis: IntArray, count: IntArray,
               gap: FloatArray) -> bool:  # pragma: no cover
    """Whether self pair p's table proves it apart in every lane: its spheres (`self_pair_tables`)
    or its convex pieces, and so its meshes (`piece_gaps`). `cells` from `table_cells`."""
    if offset[p] < 0:
        return False
    a0, a1, base, inner = axis[p, 0], axis[p, 1], offset[p], count[p, 1]
    clear = True
    for w in range(n):
        i0, i1 = cells[a0, w], cells[a1, w]
        # Off the grid the bound does not hold; the read stays inside the table either way.
        inside = (i0 >= 0) & (i1 >= 0)
        clear &= inside & (gap[base + max(i0, 0) * inner + max(i1, 0)] > CONTACT_EPS_M + ROUNDING_GUARD_M)
    return clear


@nb.njit(cache=True)
def lane_pair_clear(w: int, p: int, cells: IntArray, offset: IntArray, axis: IntArray, count: IntArray,
                    gap: FloatArray) -> bool:  # pragma: no cover
    """`pair_clear` for lane w alone: a lane the table proves is not flagged whatever its chunk's
    other lanes need (the pieces can prove a lane whose spheres touch)."""
    if offset[p] < 0:
        return False
    i0, i1 = cells[axis[p, 0], w], cells[axis[p, 1], w]
    return i0 >= 0 and i1 >= 0 and gap[offset[p] + i0 * count[p, 1] + i1] > CONTACT_EPS_M + ROUNDING_GUARD_M


@nb.njit(cache=True)
def _group_near(n: int, frames: FloatArray, joint: int, center_joint: FloatArray, g: int, radius: float,
                bound_lanes: FloatArray, link: int, bound_self: FloatArray) -> bool:  # pragma: no cover (compiled)
    """Whether link `link`'s bounding sphere is within contact of pair group g's sphere (center
    center_joint[g] in joint frame `joint`, `radius`) in any of the n lanes."""
    cx, cy, cz = center_joint[g, 0], center_joint[g, 1], center_joint[g, 2]
    reach = bound_self[link] + radius + CONTACT_EPS_M
    near = False
    for w in range(n):
        dx = frames[joint, 9, w] + frames[joint, 0, w] * cx + frames[joint, 1, w] * cy + frames[joint, 2, w] * cz \
            - bound_lanes[link, 0, w]
        dy = frames[joint, 10, w] + frames[joint, 3, w] * cx + frames[joint, 4, w] * cy + frames[joint, 5, w] * cz \
            - bound_lanes[link, 1, w]
        dz = frames[joint, 11, w] + frames[joint, 6, w] * cx + frames[joint, 7, w] * cy + frames[joint, 8, w] * cz \
            - bound_lanes[link, 2, w]
        near |= dx * dx + dy * dy + dz * dz <= reach * reach
    return near


@nb.njit(cache=True)
def _any_set(n: int, flags: BoolArray) -> bool:  # pragma: no cover (compiled)
    found = False
    for w in range(n):
        found |= flags[w]
    return found


@nb.njit(cache=True)
def _all_set(n: int, flags: BoolArray) -> bool:  # pragma: no cover (compiled)
    done = True
    for w in range(n):
        done &= flags[w]
    return done


@nb.njit(cache=True)
def place_lanes(n: int, frames: FloatArray, joint: int, centers_joint: FloatArray, first: int, end: int,
                out: FloatArray) -> None:  # pragma: no cover
    """out[s, :, w] = world position of centers_joint[s] (joint frame) for s in [first, end)."""
    for s in range(first, end):
        cx, cy, cz = centers_joint[s, 0], centers_joint[s, 1], centers_joint[s, 2]
        for w in range(n):
            out[s, 0, w] = frames[joint, 9, w] + frames[joint, 0, w] * cx + frames[joint, 1, w] * cy + frames[joint, 2, w] * cz
            out[s, 1, w] = frames[joint, 10, w] + frames[joint, 3, w] * cx + frames[joint, 4, w] * cy + frames[joint, 5, w] * cz
            out[s, 2, w] = frames[joint, 11, w] + frames[joint, 6, w] * cx + frames[joint, 7, w] * cy + frames[joint, 8, w] * cz


@nb.njit(cache=True)
def _ensure_placed(n: int, li: int, placed: BoolArray, frames: FloatArray, link_joint: IntArray, centers_joint: FloatArray,
                   link_start: IntArray, sphere_lanes: FloatArray) -> None:  # pragma: no cover (compiled)
    # Spheres are placed per link on first need: a link whose bound touches nothing needs none.
    if not placed[li]:
        place_lanes(n, frames, link_joint[li], centers_joint, link_start[li], link_start[li + 1], sphere_lanes)
        placed[li] = True


@nb.njit(cache=True, fastmath={"contract"})
def lanes_suspect(lanes: int, world: LaneWorld, stop_at_first_lane: bool) -> None:  # pragma: no cover (compiled)
    """world.flags[w] = whether any sphere of lane w's state is within contact (FCL must decide).

    Every loop runs over `lanes` lanes: an edge fills whole vectors (unused lanes hold a copy of a
    used one), a single state takes one lane. The count is a run-time
    value on purpose: with a constant count the compiler unrolls the short loops into scalar code
    instead (measured 15 % slower per state).

    Multiply-adds may fuse ("contract", ~10 % faster): it changes results by rounding only, far
    inside the spheres' 0.25 mm tolerance.

    With `stop_at_first_lane`, checking stops once any lane is flagged (the other lanes' flags
    then are incomplete): enough to find one suspect of an edge. Stopping only once lane 0 was
    flagged let a blocked chunk run to its end: a tree edge's far end is a state the planner has
    just found valid, so its first suspect is seldom lane 0, and a blocked UR5 edge among shelves
    cost 31 us instead of 12 (the GJK proofs of every other lane near a board).

    Args:
        lanes: Lanes to check, 1..LANES; the states are in world.cos_lanes, sin_lanes and q_lanes,
            the clearance each keeps from the occupied voxels in world.lane_clearance.
        world: The robot, scene and scratch buffers (`LaneWorld`).
    """
    frames, sphere_lanes, bound_lanes, placed = world.frames, world.sphere_lanes, world.bound_lanes, world.placed
    near, distance, att_lanes, flags = world.near, world.distance, world.att_lanes, world.flags
    centers_joint, radii_self, radii_world = world.centers_joint, world.radii_self, world.radii_world
    link_start, bound_center_joint, bound_self = world.link_start, world.bound_center_joint, world.bound_self
    bound_world, self_pairs, link_joint = world.bound_world, world.self_pairs, world.link_joint
    obj_kind, obj_rotation, obj_translation = world.obj_kind, world.obj_rotation, world.obj_translation
    obj_param, obj_bound = world.obj_param, world.obj_bound
    has_grid, grid, grid_origin, grid_voxel = world.has_grid, world.grid, world.grid_origin, world.grid_voxel
    grid_box, occupied, lane_clearance = world.grid_box, world.occupied, world.lane_clearance
    fine, fine_origin, fine_voxel = world.fine, world.fine_origin, world.fine_voxel
    fine_slot, fine_box, grid_column = world.fine_slot, world.fine_box, world.grid_column
    att_center_joint, att_radius, att_radius_world = world.att_center_joint, world.att_radius, world.att_radius_world
    att_joint, att_skip = world.att_joint, world.att_skip
    pair_offset, pair_axis, pair_count, pair_gap = world.pair_offset, world.pair_axis, world.pair_count, world.pair_gap
    axis_cells = world.axis_cells
    pair_near = world.pair_near
    forward_joints_lanes(lanes, world.cos_lanes, world.sin_lanes, world.q_lanes, world.parent, world.joint_type,
                         world.q_slot, world.coefficients, world.base_joint, world.joint_from_base, frames)
    n_links = link_start.shape[0] - 1
    for w in range(lanes):
        flags[w] = False
    for li in range(n_links):
        placed[li] = False
        place_lanes(lanes, frames, link_joint[li], bound_center_joint, li, li + 1, bound_lanes)
    # Robot vs primitives: link bounding sphere first, then the link's spheres.
    for li in range(n_links):
        for k in range(obj_kind.shape[0]):
            reach = bound_world[li] + obj_bound[k]
            r2 = reach * reach
            ox, oy, oz = obj_translation[k, 0], obj_translation[k, 1], obj_translation[k, 2]
            close = False
            for w in range(lanes):
                dx, dy, dz = bound_lanes[li, 0, w] - ox, bound_lanes[li, 1, w] - oy, bound_lanes[li, 2, w] - oz
                close |= dx * dx + dy * dy + dz * dz <= r2
            if not close:
                continue
            object_distance_lanes(lanes, bound_lanes, li, k, obj_kind, obj_rotation, obj_translation, obj_param, distance)
            if not _any_within(lanes, distance, bound_world[li]):
                continue
            _ensure_placed(lanes, li, placed, frames, link_joint, centers_joint, link_start, sphere_lanes)
            for w in range(lanes):
                pair_near[w] = False
            for s in range(link_start[li], link_start[li + 1]):
                object_distance_lanes(lanes, sphere_lanes, s, k, obj_kind, obj_rotation, obj_translation, obj_param,
                                       distance)
                _flag_within(lanes, distance, radii_world[s] + CONTACT_EPS_M, pair_near)
            for w in range(lanes):
                # A box face with the whole (padded) link hull beyond it, or else GJK's proof that
                # the hull keeps off the object, clears what the spheres flag.
                if pair_near[w] and not flags[w] and not (obj_kind[k] == BOX and link_outside_box(
                        w, li, k, frames, link_joint, world.sep_link_whole, world.sep_vertex_start, world.sep_vertices,
                        obj_rotation, obj_translation, obj_param, world.sep_link_growth[li])) and not link_keeps_off_object(
                        w, li, k, frames, link_joint, world.sep_link_whole, world.sep_piece_link, world.sep_vertex_start,
                        world.sep_vertices, obj_kind, obj_rotation, obj_translation, obj_param,
                        world.sep_link_growth[li] + GUARD_M):
                    flags[w] = True
                    if stop_at_first_lane:
                        break
            if _all_set(lanes, flags) or (stop_at_first_lane and _any_set(lanes, flags)):
                return
        if has_grid:
            for w in range(lanes):
                if flags[w] or voxel_distance(bound_lanes[li, 0, w], bound_lanes[li, 1, w], bound_lanes[li, 2, w],
                                               grid, grid_origin, grid_voxel, grid_box) > bound_world[li] + lane_clearance[w]:
                    continue
                _ensure_placed(lanes, li, placed, frames, link_joint, centers_joint, link_start, sphere_lanes)
                for s in range(link_start[li], link_start[li + 1]):
                    x, y, z = sphere_lanes[s, 0, w], sphere_lanes[s, 1, w], sphere_lanes[s, 2, w]
                    reach = radii_world[s] + lane_clearance[w] + CONTACT_EPS_M
                    if voxel_distance(x, y, z, grid, grid_origin, grid_voxel, grid_box) <= reach and touches_cells(
                            x, y, z, reach, occupied, grid_origin, grid_voxel, fine, fine_origin, fine_voxel, fine_slot,
                            fine_box, grid_column):
                        flags[w] = True
                        break
                if flags[w] and stop_at_first_lane:
                    break
            if _all_set(lanes, flags) or (stop_at_first_lane and _any_set(lanes, flags)):
                return
    # Self-collision, unpadded.
    # A row per link of the pair, as long as the largest link: scratch of the world, as three
    # allocations per call cost about 0.15 us of a UR5 chunk's 1 us of fixed work.
    near_a, near_b = world.near_spheres[0], world.near_spheres[1]
    pair_checked, group_end, group_radius = world.pair_checked, world.pair_group_end, world.pair_group_radius
    if pair_checked.shape[0] > 0:
        table_cells(lanes, world.q_lanes, world.axis_low, world.axis_step, world.axis_count, axis_cells)
    # Pairs in groups sharing their first link and the joint of their second (`pair_groups`):
    # one bounding-sphere test may skip a whole group.
    at = 0
    while at < pair_checked.shape[0]:
        first, at = at, group_end[at]
        if group_radius[first] >= 0.0 and not _group_near(
                lanes, frames, link_joint[self_pairs[pair_checked[first], 1]], world.pair_group_center, first,
                group_radius[first], bound_lanes, self_pairs[pair_checked[first], 0], bound_self):
            continue
        for k in range(first, at):
            p = pair_checked[k]
            la, lb = self_pairs[p, 0], self_pairs[p, 1]
            if not points_within(lanes, bound_lanes, la, bound_lanes, lb, bound_self[la] + bound_self[lb], near):
                continue
            if pair_clear(lanes, p, axis_cells, pair_offset, pair_axis, pair_count, pair_gap):
                continue
            _ensure_placed(lanes, la, placed, frames, link_joint, centers_joint, link_start, sphere_lanes)
            _ensure_placed(lanes, lb, placed, frames, link_joint, centers_joint, link_start, sphere_lanes)
            # Each link's spheres against the other link's bounding sphere first, then only the near
            # ones against each other: most spheres of a pair whose bounds overlap are far from the
            # other link, on both sides (a 12-sphere upper arm beside a 4-sphere wrist).
            n_near_a = 0
            for sa in range(link_start[la], link_start[la + 1]):
                if points_within(lanes, sphere_lanes, sa, bound_lanes, lb, radii_self[sa] + bound_self[lb], near):
                    near_a[n_near_a] = sa
                    n_near_a += 1
            if n_near_a == 0:
                continue
            n_near_b = 0
            for sb in range(link_start[lb], link_start[lb + 1]):
                if points_within(lanes, sphere_lanes, sb, bound_lanes, la, radii_self[sb] + bound_self[la], near):
                    near_b[n_near_b] = sb
                    n_near_b += 1
            touching = False
            for w in range(lanes):
                pair_near[w] = False
            for i in range(n_near_a):
                sa = near_a[i]
                for j in range(n_near_b):
                    sb = near_b[j]
                    if points_within(lanes, sphere_lanes, sa, sphere_lanes, sb, radii_self[sa] + radii_self[sb], near):
                        touching = True
                        for w in range(lanes):
                            pair_near[w] |= near[w]
            if not touching:
                continue
            for w in range(lanes):
                # A lane flagged already needs no proof; one a plane separates is clear of this pair.
                if pair_near[w] and not flags[w] and not lane_pair_clear(
                        w, p, axis_cells, pair_offset, pair_axis, pair_count, pair_gap) and not pair_separated(
                        w, p, frames, link_joint, world.sep_pair_whole, world.sep_pair_range, world.sep_sub_piece,
                        world.sep_sub_start, world.sep_side, world.sep_plane, world.sep_piece_link, world.sep_piece_center,
                        world.sep_piece_radius, world.sep_vertex_start, world.sep_vertices):
                    flags[w] = True
                    if stop_at_first_lane:
                        break
            if _all_set(lanes, flags) or (stop_at_first_lane and _any_set(lanes, flags)):
                return
    # Attached spheres: against the world (padded) and the robot links they may not touch.
    n_attached = att_radius.shape[0]
    if n_attached == 0:
        return
    for a in range(n_attached):
        place_lanes(lanes, frames, att_joint[a], att_center_joint, a, a + 1, att_lanes)
    for w in range(lanes):
        for a in range(n_attached):
            if flags[w]:
                break
            x, y, z = att_lanes[a, 0, w], att_lanes[a, 1, w], att_lanes[a, 2, w]
            reach = att_radius_world[a] + CONTACT_EPS_M
            for k in range(obj_kind.shape[0]):
                if object_distance(x, y, z, k, obj_kind, obj_rotation, obj_translation, obj_param) <= reach:
                    flags[w] = True
                    break
            reach += lane_clearance[w]
            if flags[w] or (has_grid and voxel_distance(x, y, z, grid, grid_origin, grid_voxel, grid_box) <= reach
                            and touches_cells(x, y, z, reach, occupied, grid_origin, grid_voxel, fine, fine_origin,
                                              fine_voxel, fine_slot, fine_box, grid_column)):
                flags[w] = True
                break
            for lo in range(n_links):
                if att_skip[a, lo]:
                    continue
                dx, dy, dz = x - bound_lanes[lo, 0, w], y - bound_lanes[lo, 1, w], z - bound_lanes[lo, 2, w]
                reach = att_radius[a] + bound_self[lo] + CONTACT_EPS_M
                if dx * dx + dy * dy + dz * dz > reach * reach:
                    continue
                _ensure_placed(lanes, lo, placed, frames, link_joint, centers_joint, link_start, sphere_lanes)
                for s in range(link_start[lo], link_start[lo + 1]):
                    dx, dy, dz = x - sphere_lanes[s, 0, w], y - sphere_lanes[s, 1, w], z - sphere_lanes[s, 2, w]
                    reach = att_radius[a] + radii_self[s] + CONTACT_EPS_M
                    if dx * dx + dy * dy + dz * dz <= reach * reach:
                        flags[w] = True
                        break
                if flags[w]:
                    break
