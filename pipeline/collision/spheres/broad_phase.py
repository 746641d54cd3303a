"""Conservative sphere broad phase for collision checking, compiled with numba (as VAMP does).

Each collision link is covered by spheres (`pipeline/sphere_model.py`); a state is "suspect" when
any sphere comes within contact of a scene primitive, an occupied voxel, a sphere of another
link (self-collision pairs of `CollisionWorld`) or an attached sphere. Sphere-free implies
FCL-free, so a cleared state needs no exact check; a suspect state must be asked of FCL.

Why hand-written numba instead of FCL for this: on MBM `box` problem 1 (Panda, 7 obstacles,
random states) an FCL check of a state cost ~80 us (Pinocchio FK from Python, numpy culling,
one python-fcl call per near pair), while a state inside the compiled edge loop (FK, 101
spheres vs the obstacles, the self pairs; 16 states at a time, `broad_phase_lanes`) costs
~0.45 us, and a call from Python ~1 us more; a whole 1 rad edge at 0.01 rad (101 states) is
one call of ~50 us against ~14 ms of FCL for a free edge. FCL stays the exact check for
suspects, asked only about the pairs whose spheres touch (`suspect_pairs`).

Robot-vs-world spheres are grown so they contain the PADDED hulls FCL uses: `grow_hull` pushes
vertices out by up to ~1.8x the padding, so each shape's world radii are refitted to its grown
hull by power cells (`radii_covering`: each sphere grows by what its part of the grown hull
needs, at least the padding), or, where that is not smaller, all grow by the Hausdorff distance
from the grown hull to the hull (measured with FCL at construction). Self-collision uses the
unpadded spheres, as `CollisionWorld` does.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from robonav.pipeline.collision.spheres.edge_lanes import edge_suspect_steps, state_suspect_tiered
from robonav.pipeline.collision.spheres.grid_layers import (
    NO_BOXES,
    NO_SLOTS,
    VoxelLayer,
    cell_boxes,
    cell_layer,
    column_ranges,
    field_to_cell_boxes,
    voxel_layer,
)
from robonav.pipeline.collision.spheres.kernels import BOX, CAPSULE, CONTACT_EPS_M, CYLINDER, SPHERE
from robonav.pipeline.collision.spheres.lanes import LANES, LaneWorld
from robonav.pipeline.collision.spheres.pairs import clearance_pair_bounds, suspect_pairs_of_state
from robonav.pipeline.collision.spheres.piece_gaps import cached_pair_tables
from robonav.pipeline.collision.spheres.self_pair_tables import axis_grids, no_pair_tables
from robonav.pipeline.collision.spheres.separating_planes import (
    SeparatingPlanes,
    cached_separating_planes,
)
from robonav.pipeline.collision.spheres.sphere_model import (
    RobotSphereModel,
    padded_growth_m,
    robot_sphere_model,
    world_radii,
)
from robonav.pipeline.collision.spheres.visited_pairs import pair_groups, pairs_apart_everywhere
from robonav.pipeline.robot.lane_kinematics import LinkKinematics
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.types import FloatArray

_PLANE_FIELDS = (("pair_whole", "pair_whole"), ("pair_range", "pair_range"), ("sub_piece", "sub_piece"), ("sub_start", "sub_start"), ("side", "side"),
                 ("plane", "plane_joint"), ("piece_link", "piece_link"), ("piece_center", "piece_center_joint"),
                 ("piece_radius", "piece_radius"), ("vertex_start", "vertex_start"), ("vertices", "vertices_joint"),
                 ("link_whole", "link_whole"))


class SphereBroadPhase:
    """Sphere model of one robot plus the world it is checked against, all precompiled arrays.

    Not thread-safe (it reuses scratch buffers).
    """

    def __init__(self, robot: RobotModel, *, padding_m: float = 0.0,
                 self_pairs: Sequence[tuple[str, str]] | None = None,
                 sphere_model: RobotSphereModel | None = None, self_pair_tables: bool = True,
                 separating_planes: bool = True) -> None:
        """Build spheres, kinematics and the self-collision pair list.

        Args:
            robot: Kinematics and link geometry.
            padding_m: Robot-vs-world padding of the FCL hulls this must stay conservative to [m].
            self_pairs: Link pairs checked for self-collision (`CollisionWorld.self_collision_pairs`);
                None derives them the same way (all pairs minus adjacent and allowed ones).
            sphere_model: Spheres to use; None builds (or reuses the cached) default cover.
            self_pair_tables: Skip self pairs where a precomputed gap bound proves their spheres
                apart (`self_pair_tables`; the answers are the same either way, so False is
                for testing that).
            separating_planes: Clear self pairs whose spheres touch where a plane separates
                their hulls (`separating_planes`; False flags them, for testing that).
        """
        if not (math.isfinite(padding_m) and padding_m >= 0):
            raise ValueError(f"padding_m must be finite and >= 0, got {padding_m}")
        self._robot = robot
        self._kin = LinkKinematics.from_robot(robot)
        model = sphere_model if sphere_model is not None else robot_sphere_model(robot)
        self._model = model
        links = robot.collision_link_names
        shapes = [s for link in links for s in robot.link_collision_shapes[link]]
        growth = np.array([padded_growth_m(s.hull_vertices, s.hull_triangles, padding_m) for s in shapes])
        # Fresh writable C arrays: numba compiles one specialisation per array layout/writability,
        # and a lazy compile triggered from an OMPL worker thread can deadlock on the GIL.
        self._centers_link = np.array(model.centers_link_m, dtype=np.float64, order="C")
        self._radii_self = np.array(model.radii_m, dtype=np.float64)
        self._radii_world = world_radii(shapes, model, growth, padding_m)
        # How far the padded hulls FCL uses reach beyond a link's own (separating_planes' box test).
        self._link_growth = np.array([max((growth[s] for s in np.flatnonzero(np.array([sh.link for sh in shapes]) == link)),
                                          default=0.0) for link in links], dtype=np.float64)
        self._sphere_link = np.array(model.link_index, dtype=np.int64)
        n_links = len(links)
        starts = np.searchsorted(self._sphere_link, np.arange(n_links + 1))
        self._link_start = starts.astype(np.int64)
        # One bounding sphere per link (first level of the two-level check).
        bound_center = np.zeros((n_links, 3))
        bound_self = np.zeros(n_links)
        bound_world = np.zeros(n_links)
        for li in range(n_links):
            c = self._centers_link[starts[li]:starts[li + 1]]
            mid = 0.5 * (c.min(axis=0) + c.max(axis=0)) if len(c) else np.zeros(3)
            bound_center[li] = mid
            dist = np.linalg.norm(c - mid, axis=1)
            bound_self[li] = float(np.max(dist + self._radii_self[starts[li]:starts[li + 1]], initial=0.0))
            bound_world[li] = float(np.max(dist + self._radii_world[starts[li]:starts[li + 1]], initial=0.0))
        self._bound_self, self._bound_world = bound_self, bound_world
        if self_pairs is None:
            ignored = set(robot.adjacent_link_pairs) | {tuple(sorted(p)) for p in robot.config.allowed_collision_pairs}
            self_pairs = [(a, b) for i, a in enumerate(links) for b in links[i + 1:] if tuple(sorted((a, b))) not in ignored]
        self._self_pairs = np.array([(links.index(a), links.index(b)) for a, b in self_pairs],
                                    dtype=np.int64).reshape(-1, 2)
        self._padding_m = float(padding_m)
        # The lane kernels place spheres straight from joint frames: link placements folded in.
        self._link_joint = np.array(self._kin.link_joint, dtype=np.int64)
        self._centers_joint = _to_joint_frame(self._kin, self._sphere_link, self._centers_link)
        self._bound_center_joint = _to_joint_frame(self._kin, np.arange(n_links), bound_center)
        self._kin_lane_args = self._kin.lane_arrays()
        self._pair_tables = (cached_pair_tables(robot, self._kin, self._centers_joint, self._radii_self,
                                                self._link_start, self._self_pairs, CONTACT_EPS_M)
                             if self_pair_tables else no_pair_tables(self._self_pairs.shape[0]))
        self._axis_grids = axis_grids(self._pair_tables, robot.dof)
        # The pairs the compiled check visits: not those a table proves apart at every state.
        self._pair_groups = pair_groups(self._self_pairs, np.flatnonzero(~pairs_apart_everywhere(
            self._pair_tables, robot.lower_limits_rad, robot.upper_limits_rad, CONTACT_EPS_M)),
            self._link_joint, self._bound_center_joint, bound_self)
        self._planes = (cached_separating_planes(robot, self._kin, self._centers_link, self._radii_self, self._link_start,
                                                 self._self_pairs)
                        if separating_planes else SeparatingPlanes.none(self._self_pairs.shape[0], n_links))
        # Scratch buffers (no allocation per call).
        dof = robot.dof
        self._lane_scratch = dict(
            cos_lanes=np.zeros((dof, LANES)), sin_lanes=np.zeros((dof, LANES)), q_lanes=np.zeros((dof, LANES)),
            flags=np.zeros(LANES, dtype=np.bool_), frames=self._kin.new_lane_frames(LANES),
            sphere_lanes=np.zeros((self._centers_link.shape[0], 3, LANES)), bound_lanes=np.zeros((n_links, 3, LANES)),
            placed=np.zeros(n_links, dtype=np.bool_), near=np.zeros(LANES, dtype=np.bool_), distance=np.zeros(LANES),
            pair_near=np.zeros(LANES, dtype=np.bool_), lane_clearance=np.zeros(LANES),
            lane_tier=np.zeros(LANES, dtype=np.int64), axis_cells=np.zeros((dof + 1, LANES), dtype=np.int64),
            near_spheres=np.zeros((2, int(np.max(np.diff(starts), initial=0))), dtype=np.int64))
        self._step_buffer = np.zeros((1, 2), dtype=np.int64)
        self._queue, self._no_anchors = np.zeros((1, 2), dtype=np.int64), np.zeros((0, dof))
        self.clear_objects()
        self.clear_occupancy()
        self._attached: dict[str, tuple[int, FloatArray, FloatArray, tuple[str, ...]]] = {}
        self._rebuild_attached()
        # Compile (or load from numba's cache) now, on the constructing thread.
        home = robot.home_position_rad
        self.state_suspect(home)
        self.edge_suspects(home, home, 1.0)
        self.suspect_pairs(home)
        self.clearance_pair_bounds_m(home[None])

    # --- world ---------------------------------------------------------------------------------

    @property
    def sphere_model(self) -> RobotSphereModel:
        return self._model

    @property
    def sphere_count(self) -> int:
        return int(self._radii_self.shape[0])

    def set_objects(self, objects: Sequence[SceneObject]) -> None:
        """Replace the obstacles (world frame). A mesh is checked as its local bounding box, which contains it."""
        kinds, rotations, translations, params, bounds = [], [], [], [], []
        for obj in objects:
            pose = obj.world_from_object
            rotation, translation = pose[:3, :3], pose[:3, 3]
            if obj.type == "box":
                kind, param = BOX, 0.5 * np.array(obj.size_m, dtype=np.float64)
            elif obj.type == "sphere":
                kind, param = SPHERE, np.array([obj.radius_m, 0.0, 0.0])
            elif obj.type == "cylinder":
                kind, param = CYLINDER, np.array([obj.radius_m, 0.5 * obj.length_m, 0.0])
            elif obj.type == "capsule":
                kind, param = CAPSULE, np.array([obj.radius_m, 0.5 * obj.length_m, 0.0])
            else:
                # Any other shape (meshes) as its local axis-aligned box: conservative.
                center, half = obj.local_bounds_m
                kind, param = BOX, np.maximum(np.asarray(half, dtype=np.float64), 1e-9)
                translation = translation + rotation @ np.asarray(center, dtype=np.float64)
            kinds.append(kind)
            rotations.append(rotation)
            translations.append(translation)
            params.append(param)
            extent = float(np.linalg.norm(param)) if kind == BOX else float(param[0] + param[1])
            bounds.append(extent)
        self._obj_kind = np.array(kinds, dtype=np.int64)
        self._obj_rotation = np.array(rotations, dtype=np.float64).reshape(-1, 3, 3)
        self._obj_translation = np.array(translations, dtype=np.float64).reshape(-1, 3)
        self._obj_param = np.array(params, dtype=np.float64).reshape(-1, 3)
        self._obj_bound = np.array(bounds, dtype=np.float64)
        self._refresh_args()

    def clear_objects(self) -> None:
        self.set_objects([])

    def set_occupied_voxels(self, centers_m: FloatArray, voxel_size_m: float, clearance_m: float = 0.0, *,
                            surface_m: FloatArray | None = None, surface_cell_m: float | None = None,
                            tiers: int = 1) -> None:
        """Replace the occupancy with cubes of side `voxel_size_m` at `centers_m` (N, 3), world frame [m].

        `clearance_m` is a distance the spheres must keep from what is occupied, on top of their
        own (padded) radii [m]: a map's inflation applied to the robot instead of the voxels.
        Queries of tier t (0..`tiers`) keep clearance_m * t / tiers; the default tier is the last
        (`CollisionWorld`'s clearance that shrinks near a query's start and goals).

        `surface_m` (M, 3), points inside the cubes: then what is occupied is the cells of side
        `surface_cell_m` holding them (a grid nested in the voxels', e.g. 5 mm in 2 cm), and
        the cubes' distance field only culls.

        Builds a Euclidean distance field on a grid aligned with the voxels, covering them plus a
        margin. A lookup at point p in cell c returns edt(c) - |p - center(c)| - half voxel
        diagonal, a lower bound on the distance from p to any occupied cube; outside the grid the
        distance to the occupied cubes' bounding box is used.
        """
        centers = np.asarray(centers_m, dtype=np.float64).reshape(-1, 3)
        if not (math.isfinite(voxel_size_m) and voxel_size_m > 0):
            raise ValueError(f"voxel_size_m must be finite and > 0, got {voxel_size_m}")
        if not (math.isfinite(clearance_m) and clearance_m >= 0) or tiers < 1:
            raise ValueError(f"clearance_m must be finite and >= 0 and tiers >= 1, got {clearance_m}, {tiers}")
        if centers.shape[0] == 0:
            self.clear_occupancy()
            return
        low = centers.min(axis=0)
        self._coarse = voxel_layer(np.round((centers - low) / voxel_size_m).astype(np.int64), float(voxel_size_m),
                                    int(math.ceil(0.25 / voxel_size_m)) + 2, low)
        self._fine = None
        self._fine_slot, self._fine_box = NO_SLOTS, NO_BOXES
        if surface_m is not None:
            surface = np.asarray(surface_m, dtype=np.float64).reshape(-1, 3)
            ratio = voxel_size_m / surface_cell_m if surface_cell_m is not None and surface_cell_m > 0 else math.nan
            if not (math.isfinite(ratio) and abs(ratio - round(ratio)) < 1e-6 and round(ratio) >= 1):
                raise ValueError(f"surface_cell_m must divide voxel_size_m {voxel_size_m}, got {surface_cell_m}")
            if surface.shape[0]:
                # Cells on the grid anchored at 0, like octomap's voxels: they nest in the voxels.
                cell = float(surface_cell_m)  # type: ignore[arg-type]
                self._fine = cell_layer(np.floor(surface / cell).astype(np.int64), cell)
                self._fine_slot, self._fine_box = cell_boxes(self._fine, self._coarse)
                # Exact as far as a sphere's test reads it (its reach plus the lookup's offset).
                reach = float(np.max(self._radii_world, initial=0.0)) + clearance_m + math.sqrt(3.0) * voxel_size_m
                self._coarse = field_to_cell_boxes(self._coarse, self._fine, self._fine_slot, self._fine_box, reach)
        # The kernels test the voxels with cells, or the voxels themselves when cells are as large.
        cells = self._fine is not None and self._fine.voxel != self._coarse.voxel
        self._grid_column = column_ranges(self._fine_slot >= 0 if cells else self._coarse.occupied)
        self._has_grid = True
        self._clearances = [float(clearance_m) * t / tiers for t in range(tiers + 1)]
        self._refresh_args()

    def clear_occupancy(self) -> None:
        self._coarse = VoxelLayer(np.zeros((1, 1, 1)), np.zeros(3), 1.0, np.zeros((2, 3)), np.zeros((1, 1, 1), dtype=np.bool_))
        self._fine = None
        self._fine_slot, self._fine_box = NO_SLOTS, NO_BOXES
        self._grid_column = column_ranges(self._coarse.occupied)
        self._has_grid = False
        self._clearances = [0.0]
        self._refresh_args()

    def set_attached_spheres(self, name: str, link: str, centers_link_m: FloatArray, radii_m: FloatArray,
                             touch_links: Sequence[str] = ()) -> None:
        """Add (or replace) spheres rigid on `link`, e.g. the cover of a grasped object.

        They are checked against the world (padded like the robot) and against robot links
        other than `link` and `touch_links`.

        Args:
            name: Key for `remove_attached`.
            link: A collision link name.
            centers_link_m: (A, 3) centers in the LINK frame [m].
            radii_m: (A,) radii [m].
            touch_links: Links the object may touch (ignored for it).
        """
        links = self._robot.collision_link_names
        for label in (link, *touch_links):
            if label not in links:
                raise ValueError(f"'{label}' is not a collision link ({list(links)})")
        centers = np.asarray(centers_link_m, dtype=np.float64).reshape(-1, 3)
        radii = np.asarray(radii_m, dtype=np.float64).reshape(-1)
        if radii.shape[0] != centers.shape[0] or np.any(radii < 0):
            raise ValueError(f"need one radius >= 0 per center, got {radii.shape[0]} radii for {centers.shape[0]} centers")
        self._attached[name] = (links.index(link), centers, radii, tuple(touch_links))
        self._rebuild_attached()

    def remove_attached(self, name: str) -> None:
        """Forget attached spheres added under `name` (no-op when absent)."""
        self._attached.pop(name, None)
        self._rebuild_attached()

    def _rebuild_attached(self) -> None:
        links = self._robot.collision_link_names
        centers, radii, owner, rows = [], [], [], []
        for link_index, c, r, touch in self._attached.values():
            skip = np.zeros(len(links), dtype=np.bool_)
            skip[link_index] = True
            for t in touch:
                skip[links.index(t)] = True
            centers.append(c)
            radii.append(r)
            owner.append(np.full(len(r), link_index, dtype=np.int64))
            rows.append(np.repeat(skip[None], len(r), axis=0))
        center_link = np.vstack(centers).reshape(-1, 3) if centers else np.zeros((0, 3))
        self._att_radius = np.concatenate(radii) if radii else np.zeros(0)
        self._att_radius_world = self._att_radius + self._padding_m
        att_link = np.concatenate(owner) if owner else np.zeros(0, dtype=np.int64)
        self._att_skip = np.vstack(rows) if rows else np.zeros((0, len(links)), dtype=np.bool_)
        self._att_center_joint = _to_joint_frame(self._kin, att_link, center_link)
        self._att_joint = self._link_joint[att_link]
        self._att_lanes = np.zeros((self._att_radius.shape[0], 3, LANES))
        self._refresh_args()

    # --- queries -------------------------------------------------------------------------------

    def _refresh_args(self) -> None:
        # Built once per world change (never per call): the kernels read this one object.
        if not hasattr(self, "_att_lanes") or not hasattr(self, "_has_grid") or not hasattr(self, "_obj_kind"):
            return
        # Every tier keeps its clearance from the surface cells when there are some (the seen
        # points, not the voxels that quantise them), else from the voxels.
        self._tier_clearance = np.array(self._clearances, dtype=np.float64)
        worlds = {c: self._new_lane_world(c, self._fine) for c in set(self._clearances)}
        self._lane_worlds = [worlds[c] for c in self._clearances]
        self._lane_world = self._lane_worlds[-1]
        n_links = self._link_start.shape[0] - 1
        self._pair_outputs = (np.zeros((n_links, self._obj_kind.shape[0]), dtype=np.bool_),
                              np.zeros(n_links, dtype=np.bool_), np.zeros(self._self_pairs.shape[0], dtype=np.bool_),
                              np.zeros((n_links, 4, 4)))

    def _new_lane_world(self, grid_clearance: float, fine: VoxelLayer | None) -> LaneWorld:
        parent, joint_type, q_slot, coefficients, base_joint, joint_from_base = self._kin_lane_args
        tables = self._pair_tables
        axis_low, axis_step, axis_count, axis = self._axis_grids
        layer = self._coarse
        fine = fine or layer
        return LaneWorld(
            parent=parent, joint_type=joint_type, q_slot=q_slot, coefficients=coefficients, base_joint=base_joint,
            joint_from_base=joint_from_base, centers_joint=self._centers_joint, radii_self=self._radii_self,
            radii_world=self._radii_world, link_start=self._link_start, bound_center_joint=self._bound_center_joint,
            bound_self=self._bound_self, bound_world=self._bound_world, self_pairs=self._self_pairs,
            pair_checked=self._pair_groups[0], pair_group_end=self._pair_groups[1],
            pair_group_center=self._pair_groups[2], pair_group_radius=self._pair_groups[3],
            link_joint=self._link_joint, joint_from_link_rotation=self._kin.joint_from_link_rotation,
            joint_from_link_translation=self._kin.joint_from_link_translation_m, pair_offset=tables.offset,
            pair_axis=axis, axis_low=axis_low, axis_step=axis_step, axis_count=axis_count, pair_count=tables.count,
            pair_gap=tables.gap_m, **{f"sep_{name}": getattr(self._planes, field) for name, field in _PLANE_FIELDS},
            sep_link_growth=self._link_growth,
            obj_kind=self._obj_kind, obj_rotation=self._obj_rotation,
            obj_translation=self._obj_translation, obj_param=self._obj_param, obj_bound=self._obj_bound,
            has_grid=self._has_grid, grid=layer.field, grid_origin=layer.origin, grid_voxel=layer.voxel,
            grid_box=layer.box, occupied=layer.occupied, fine=fine.occupied, fine_origin=fine.origin,
            fine_voxel=fine.voxel, fine_slot=self._fine_slot, fine_box=self._fine_box, grid_column=self._grid_column,
            grid_clearance=float(grid_clearance), tier_clearance=self._tier_clearance,
            att_center_joint=self._att_center_joint, att_radius=self._att_radius,
            att_radius_world=self._att_radius_world, att_joint=self._att_joint,
            att_skip=self._att_skip, att_lanes=self._att_lanes, **self._lane_scratch)

    @property
    def clearances_m(self) -> tuple[float, ...]:
        """Clearance kept from the occupancy by the queries of each tier, the default last [m]."""
        return tuple(self._clearances)

    def state_suspect(self, q: FloatArray, *, tier: int = -1) -> bool:
        """True if any sphere pair at `q` (dof,) is within contact (ask FCL); False means collision-free.
        `tier` picks the clearance kept from the occupancy (see `set_occupied_voxels`)."""
        return bool(state_suspect_tiered(np.array(q, dtype=np.float64), self._lane_worlds[tier], self._no_anchors, 0.0)[0])

    def state_suspect_tiered(self, q: FloatArray, anchors: FloatArray, anchor_radius_sq: float) -> tuple[bool, int]:
        """`state_suspect` at the clearance tier of `q` (dof,) by its squared joint-space distance
        to the nearest of `anchors` (K, dof), as `edge_suspects` tiers an edge's states: (suspect,
        tier), tier -1 beyond `anchor_radius_sq`."""
        suspect, tier = state_suspect_tiered(np.array(q, dtype=np.float64), self._lane_worlds[-1], _kernel_anchors(anchors),
                                             float(anchor_radius_sq))
        return bool(suspect), int(tier)

    def suspect_pairs(self, q: FloatArray, *, tier: int = -1) -> tuple[np.ndarray, np.ndarray, np.ndarray, FloatArray]:
        """The pairs whose spheres are within contact at `q` (dof,): only these can collide in FCL.

        Returns:
            (L, K) bool: collision link l vs object k (`set_objects` order); (L,) bool: link l vs
            the occupied voxels; (P,) bool: self-collision pair p (the `self_pairs` order); and
            world_from_link (L, 4, 4) of the collision links. Buffers reused by the next call.
        """
        objects, voxels, pairs, poses = self._pair_outputs
        suspect_pairs_of_state(np.array(q, dtype=np.float64), self._lane_worlds[tier], objects, voxels, pairs, poses)
        return objects, voxels, pairs, poses

    def clearance_pair_bounds_m(self, states: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Per state of `states` (M, dof): lower bounds on the distance from each bare collision
        link to each object and to the occupied voxels, (M, L, K + 1) [m] (column K: the voxels,
        +inf without them), and the links' poses world_from_link (M, L, 4, 4)."""
        arr = np.ascontiguousarray(states, dtype=np.float64).reshape(-1, self._robot.dof)
        n_links = self._link_start.shape[0] - 1
        bounds = np.empty((arr.shape[0], n_links, self._obj_kind.shape[0] + 1))
        poses = np.empty((arr.shape[0], n_links, 4, 4))
        clearance_pair_bounds(arr, self._lane_world, bounds, poses)
        return bounds, poses

    def link_pose_stack(self, q: FloatArray) -> FloatArray:
        """world_from_link (L, 4, 4) of the collision links at `q` (dof,), compiled (`LinkKinematics`)."""
        return self._kin.link_pose_stack(q)

    def self_suspect(self, q: FloatArray) -> bool:
        """True if spheres of a self-collision pair touch at `q` (dof,) and no separating plane
        clears it (the world ignored): for probes (`CollisionWorld.sphere_self_overflag`)."""
        return bool(self.suspect_pairs(q)[2].any())

    def edge_suspects(self, q_a: FloatArray, q_b: FloatArray, resolution_rad: float, *, first_only: bool = False,
                      tier: int = -1, anchors: FloatArray | None = None, anchor_radius_sq: float = 0.0,
                      checked_rad: float = 0.0) -> tuple[np.ndarray, np.ndarray | None, int]:
        """Suspect states of the straight segment, in `CollisionWorld.motion_valid` order.

        The segment has `steps` = max(1, ceil(max|b - a| / resolution_rad)) intervals; state k is
        a + (b - a) * (k / steps). They are visited as `motion_valid` does: k = steps (q_b),
        then the interior in bisection order, then k = 0 (q_a). Every state keeps the clearance of
        `tier`, or with `anchors` (K, dof) that of its own tier (`edge_lanes.state_tier`: by its
        squared joint-space distance to the nearest anchor against `anchor_radius_sq`).

        With `checked_rad` > 0 the segment's states at that step are known free (it passed this
        check at `checked_rad`): those of its own states that are among them are not checked
        again (k = 0, m, 2m ..., m = steps / gcd(steps, c), c their count: every second state
        when `steps` = 2 c). The states themselves stay those of `resolution_rad`, so another
        check at that step (a benchmark's) sees the same states.

        Returns:
            (M,) int64 step indices k of the suspect states in visiting order (with `first_only`
            at most one: a suspect of the first chunk of `LANES` states that has one, not always
            the first of the order), with anchors (M,) int64 the tier each was checked at (else
            None: all at `tier`), and `steps`.
        """
        # Once per tree edge: the step count is left to the compiled code (numpy's reductions on
        # 7 numbers cost microseconds), and the buffers grow only when too short.
        a = np.ascontiguousarray(q_a, dtype=np.float64)
        b = np.ascontiguousarray(q_b, dtype=np.float64)
        if not resolution_rad > 0 or resolution_rad == math.inf:  # NaN fails the first test
            raise ValueError(f"resolution_rad must be finite and > 0, got {resolution_rad}")
        if not 0 <= checked_rad < math.inf:
            raise ValueError(f"checked_rad must be finite and >= 0, got {checked_rad}")
        anchored = anchors is not None and anchors.shape[0] > 0
        anchors = _kernel_anchors(anchors) if anchored else self._no_anchors
        world = self._lane_worlds[-1 if anchored else tier]
        # Plain float and bool: an int would make numba compile another specialisation.
        resolution_rad, first_only = float(resolution_rad), bool(first_only)
        count, steps = edge_suspect_steps(a, b, resolution_rad, first_only, self._step_buffer, self._queue, world,
                                          anchors, float(anchor_radius_sq), float(checked_rad))
        if count < 0:
            # order (steps + 1 entries) and the FIFO of spans (< 2 * steps + 1 entries) share `_queue`.
            self._step_buffer = np.zeros((2 * steps + 2, 2), dtype=np.int64)
            self._queue = np.zeros((2 * steps + 2, 2), dtype=np.int64)
            count, steps = edge_suspect_steps(a, b, resolution_rad, first_only, self._step_buffer, self._queue, world,
                                              anchors, float(anchor_radius_sq), float(checked_rad))
        # Most edges have no suspect: no slice and copy (read-only, shared); without anchors every
        # state was checked at `tier`, and no tiers are copied (this runs for every blocked edge).
        if count == 0:
            return _NO_STEPS, (_NO_STEPS if anchored else None), steps
        if not anchored:
            return self._step_buffer[:count, 0].copy(), None, steps
        found = self._step_buffer[:count].copy()
        return found[:, 0], found[:, 1], steps


def _kernel_anchors(anchors: FloatArray) -> FloatArray:
    """`anchors` as the compiled code takes them, writeable and C-ordered float64: another array
    type would compile another specialisation. Most callers hold such an array already, and the
    test is a tenth of `np.require`'s (once per state and edge)."""
    if anchors.flags.carray and anchors.dtype is _FLOAT64:
        return anchors
    return np.require(anchors, np.float64, ("C", "W"))


_FLOAT64 = np.dtype(np.float64)
_NO_STEPS = np.zeros(0, dtype=np.int64)
_NO_STEPS.flags.writeable = False


def _to_joint_frame(kin: LinkKinematics, link_index: np.ndarray, points_link: FloatArray) -> FloatArray:
    """(N, 3) points given in the frames of collision links `link_index` (N,), in their joints' frames."""
    index = np.asarray(link_index, dtype=np.int64)
    points = np.asarray(points_link, dtype=np.float64).reshape(-1, 3)
    rotated = np.einsum("nij,nj->ni", kin.joint_from_link_rotation[index], points)
    return np.ascontiguousarray(rotated + kin.joint_from_link_translation_m[index])
