"""One-state sphere queries per pair, for FCL and clearance (numba; see `broad_phase_lanes`).

`broad_phase_lanes` answers whether a state (or an edge's states) may collide. When one may,
these say which link-object, link-voxel and link-link pairs FCL must look at, and, for a
reported clearance, how close each link can be to each obstacle. They run one state as lane 0
of the same `LaneWorld` and kinematics.
"""

from __future__ import annotations

import math

import numba as nb

from robonav.pipeline.collision.spheres.gjk import link_keeps_off_object
from robonav.pipeline.collision.spheres.kernels import BOX, CONTACT_EPS_M, touches_cells, voxel_distance
from robonav.pipeline.collision.spheres.lanes import (
    LaneWorld,
    object_distance_lanes,
    pair_clear,
    place_lanes,
    points_within,
    table_cells,
)
from robonav.pipeline.collision.spheres.separating_planes import GUARD_M, link_outside_box, pair_separated
from robonav.pipeline.robot.lane_kinematics import forward_joints_lanes, link_pose_from_lane
from robonav.pipeline.types import BoolArray, FloatArray


@nb.njit(cache=True, fastmath={"contract"})
def suspect_pairs_of_state(q: FloatArray, world: LaneWorld, object_flags: BoolArray, voxel_flags: BoolArray,
                           self_flags: BoolArray, world_from_link: FloatArray) -> None:  # pragma: no cover (compiled)
    """Which pairs' spheres are within contact at the one state `q` (dof,), and the link poses.

    The pairs FCL must look at, and no others: spheres that touch nothing clear their link.

    Args:
        q: (dof,) state.
        world: The robot and scene (`LaneWorld`).
        object_flags: (L, K) bool output: link l's spheres touch object k.
        voxel_flags: (L,) bool output: link l's spheres touch an occupied voxel.
        self_flags: (P,) bool output: the spheres of self-collision pair p touch.
        world_from_link: (L, 4, 4) output: the collision links' poses.
    """
    cos_lanes, sin_lanes, q_lanes = world.cos_lanes, world.sin_lanes, world.q_lanes
    for j in range(q.shape[0]):
        cos_lanes[j, 0], sin_lanes[j, 0], q_lanes[j, 0] = math.cos(q[j]), math.sin(q[j]), q[j]
    frames, sphere_lanes, bound_lanes, distance = world.frames, world.sphere_lanes, world.bound_lanes, world.distance
    near = world.near
    link_start, link_joint, radii_world, radii_self = world.link_start, world.link_joint, world.radii_world, world.radii_self
    bound_world, bound_self, self_pairs = world.bound_world, world.bound_self, world.self_pairs
    obj_kind, obj_rotation, obj_translation, obj_param = world.obj_kind, world.obj_rotation, world.obj_translation, world.obj_param
    grid, grid_origin, grid_voxel, grid_box, occupied = world.grid, world.grid_origin, world.grid_voxel, world.grid_box, world.occupied
    forward_joints_lanes(1, cos_lanes, sin_lanes, q_lanes, world.parent, world.joint_type, world.q_slot,
                         world.coefficients, world.base_joint, world.joint_from_base, frames)
    n_links = link_start.shape[0] - 1
    for li in range(n_links):
        j = link_joint[li]
        place_lanes(1, frames, j, world.bound_center_joint, li, li + 1, bound_lanes)
        place_lanes(1, frames, j, world.centers_joint, link_start[li], link_start[li + 1], sphere_lanes)
        link_pose_from_lane(frames, j, li, world.joint_from_link_rotation, world.joint_from_link_translation,
                            world_from_link, li, 0)
        for k in range(obj_kind.shape[0]):
            object_flags[li, k] = False
            object_distance_lanes(1, bound_lanes, li, k, obj_kind, obj_rotation, obj_translation, obj_param, distance)
            if distance[0] > bound_world[li]:
                continue
            for s in range(link_start[li], link_start[li + 1]):
                object_distance_lanes(1, sphere_lanes, s, k, obj_kind, obj_rotation, obj_translation, obj_param,
                                       distance)
                if distance[0] <= radii_world[s] + CONTACT_EPS_M:
                    object_flags[li, k] = True
                    break
            if object_flags[li, k] and ((obj_kind[k] == BOX and link_outside_box(
                    0, li, k, frames, link_joint, world.sep_link_whole, world.sep_vertex_start, world.sep_vertices,
                    obj_rotation, obj_translation, obj_param, world.sep_link_growth[li])) or link_keeps_off_object(
                    0, li, k, frames, link_joint, world.sep_link_whole, world.sep_piece_link, world.sep_vertex_start,
                    world.sep_vertices, obj_kind, obj_rotation, obj_translation, obj_param,
                    world.sep_link_growth[li] + GUARD_M)):
                object_flags[li, k] = False
        voxel_flags[li] = False
        if world.has_grid and voxel_distance(bound_lanes[li, 0, 0], bound_lanes[li, 1, 0], bound_lanes[li, 2, 0], grid,
                                             grid_origin, grid_voxel, grid_box) <= bound_world[li] + world.grid_clearance:
            for s in range(link_start[li], link_start[li + 1]):
                x, y, z = sphere_lanes[s, 0, 0], sphere_lanes[s, 1, 0], sphere_lanes[s, 2, 0]
                reach = radii_world[s] + world.grid_clearance + CONTACT_EPS_M
                if voxel_distance(x, y, z, grid, grid_origin, grid_voxel, grid_box) <= reach and touches_cells(
                        x, y, z, reach, occupied, grid_origin, grid_voxel, world.fine, world.fine_origin, world.fine_voxel,
                        world.fine_slot, world.fine_box, world.grid_column):
                    voxel_flags[li] = True
                    break
    table_cells(1, q_lanes, world.axis_low, world.axis_step, world.axis_count, world.axis_cells)
    for p in range(self_pairs.shape[0]):
        la, lb = self_pairs[p, 0], self_pairs[p, 1]
        self_flags[p] = False
        if not points_within(1, bound_lanes, la, bound_lanes, lb, bound_self[la] + bound_self[lb], near):
            continue
        if pair_clear(1, p, world.axis_cells, world.pair_offset, world.pair_axis, world.pair_count, world.pair_gap):
            continue
        for sa in range(link_start[la], link_start[la + 1]):
            for sb in range(link_start[lb], link_start[lb + 1]):
                if points_within(1, sphere_lanes, sa, sphere_lanes, sb, radii_self[sa] + radii_self[sb], near):
                    self_flags[p] = True
                    break
            if self_flags[p]:
                break
        if self_flags[p] and pair_separated(
                0, p, frames, link_joint, world.sep_pair_whole, world.sep_pair_range, world.sep_sub_piece,
                world.sep_sub_start, world.sep_side, world.sep_plane, world.sep_piece_link, world.sep_piece_center, world.sep_piece_radius,
                world.sep_vertex_start, world.sep_vertices):
            self_flags[p] = False


@nb.njit(cache=True)
def clearance_pair_bounds(states: FloatArray, world: LaneWorld, bounds: FloatArray, world_from_link: FloatArray) -> None:  # pragma: no cover (compiled)
    """Lower bounds on the distance between each bare collision link and each obstacle, per state.

    The bare spheres contain the bare hulls, so a link is no closer to an obstacle than its
    nearest sphere's surface; for voxels the distance field is itself a lower bound.

    Args:
        states: (M, dof) states.
        world: The robot and scene (`LaneWorld`).
        bounds: (M, L, K + 1) output [m]: column k < K for object k, column K for the occupied
            voxels (+inf without them); negative where spheres overlap an obstacle.
        world_from_link: (M, L, 4, 4) output: the collision links' poses per state.
    """
    cos_lanes, sin_lanes, q_lanes = world.cos_lanes, world.sin_lanes, world.q_lanes
    frames, sphere_lanes, distance = world.frames, world.sphere_lanes, world.distance
    link_start, link_joint, radii_self = world.link_start, world.link_joint, world.radii_self
    obj_kind, obj_rotation, obj_translation, obj_param = world.obj_kind, world.obj_rotation, world.obj_translation, world.obj_param
    n_objects = obj_kind.shape[0]
    # The states go through as lanes, as an edge's do (one state at a time cost 20 us on the UR5
    # among shelves, most of it a call per sphere and object).
    lanes = cos_lanes.shape[1]
    for first in range(0, states.shape[0], lanes):
        n = min(lanes, states.shape[0] - first)
        for w in range(n):
            for j in range(states.shape[1]):
                value = states[first + w, j]
                cos_lanes[j, w], sin_lanes[j, w], q_lanes[j, w] = math.cos(value), math.sin(value), value
        forward_joints_lanes(n, cos_lanes, sin_lanes, q_lanes, world.parent, world.joint_type, world.q_slot,
                             world.coefficients, world.base_joint, world.joint_from_base, frames)
        for li in range(link_start.shape[0] - 1):
            j = link_joint[li]
            for w in range(n):
                link_pose_from_lane(frames, j, li, world.joint_from_link_rotation, world.joint_from_link_translation,
                                    world_from_link[first + w], li, w)
                for k in range(n_objects + 1):
                    bounds[first + w, li, k] = math.inf
            place_lanes(n, frames, j, world.centers_joint, link_start[li], link_start[li + 1], sphere_lanes)
            for s in range(link_start[li], link_start[li + 1]):
                for k in range(n_objects):
                    object_distance_lanes(n, sphere_lanes, s, k, obj_kind, obj_rotation, obj_translation, obj_param,
                                          distance)
                    for w in range(n):
                        bounds[first + w, li, k] = min(bounds[first + w, li, k], distance[w] - radii_self[s])
                if world.has_grid:
                    for w in range(n):
                        gap = voxel_distance(sphere_lanes[s, 0, w], sphere_lanes[s, 1, w], sphere_lanes[s, 2, w],
                                             world.grid, world.grid_origin, world.grid_voxel, world.grid_box)
                        bounds[first + w, li, n_objects] = min(bounds[first + w, li, n_objects], gap - radii_self[s])
