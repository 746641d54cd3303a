"""The map as a planning world: a clearance that protects the path, released near the query's ends.

A map given with the voxels the sensors saw and the inflation it was published with
(`CollisionWorld.set_octree(..., seen_voxels_m, clearance_m=...)`), and optionally the seen
points (`surface_m`), is checked against its *surface*: the cells of a grid nested in the
voxels that hold seen points and the faces of the seen voxels that hold none (filled below a
surface, completed support), or the seen voxels themselves without points.

- Away from the anchors the padded links must keep `clearance_m` off the surface. The sphere
  broad phase checks exactly that (spheres grown by the clearance against the surface cells);
  the states it flags go to FCL against the inflated octree, which holds every point within
  the inflation of a seen voxel. Either test alone keeps the padded links `clearance_m` off
  what was seen, so a state one of them clears is safe by that margin.
- Toward an anchor, i.e. the start or a goal of the running query (`anchored`), the clearance
  shrinks with the joint-space (Euclidean) distance d to the nearest anchor: it is
  clearance_m * floor(TIERS * d / radius_rad) / TIERS, the full clearance from `radius_rad` on.
  Within radius_rad / TIERS of an anchor no clearance is left: the padded links must only keep
  off the surface. A goal a centimetre from a shelf is what a grasp looks like; forbidding it
  in the name of sensor noise forbids the task. GOAL_IN_COLLISION then means the goal's padded
  links touch what was seen. The spheres decide the shrunk clearances; a state they flag goes
  to FCL against the inflated octree, or within the innermost tier against an octree of the
  surface.

The allowance is what MoveIt users build by hand with `padding` and `touch_links`; here it is
explicit, bounded in joint space and argued in docs/architecture.md (unseen space is not
covered). Without anchors, or without a clearance, nothing changes.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from typing import TYPE_CHECKING

import fcl
import numpy as np
import numpy.typing as npt

from robonav.pipeline.collision.fcl_shapes import octree_of_centers
from robonav.pipeline.types import FloatArray

TIERS = 4
"""Steps of the clearance between an anchor and `radius_rad` from it."""
MIN_SPHERE_CELL_M = 0.005
"""Smallest cell of the surface grid the spheres check (one bool per cell over the scene);
FCL checks the surface on its own, finer cells."""

if TYPE_CHECKING:  # the world these methods run on
    from robonav.pipeline.collision.world import CollisionWorld


class SurfaceAllowance:
    """Map clearance and the near-anchor allowance of `CollisionWorld` (mixed into it)."""

    _surface_octree: fcl.CollisionObject | None
    _map_clearance_m: float
    _anchors: FloatArray
    _anchor_radius_sq: float

    def _init_allowance(self, dof: int) -> None:
        self._anchors = np.zeros((0, dof))
        self._anchor_radius_sq = 0.0
        self._reset_allowance()

    def _reset_allowance(self) -> None:
        self._surface_octree = None
        self._map_clearance_m = 0.0

    @property
    def map_clearance_m(self) -> float:
        """Clearance the padded links keep from the seen voxels away from the anchors [m]; 0 when
        the map came without seen voxels and its inflation (the inflated octree is then all there is)."""
        return self._map_clearance_m

    @property
    def has_surface_allowance(self) -> bool:
        """Whether near the anchors the links are checked against the surface instead of the clearance."""
        return self._surface_octree is not None

    def _set_map_layers(self: CollisionWorld, seen: FloatArray, resolution_m: float, clearance_m: float,
                        surface_m: FloatArray | None, surface_resolution_m: float | None) -> None:
        """Seen voxels with a clearance for the broad phase, and the surface octree for the anchors."""
        surface = None
        surface_res = resolution_m
        if surface_m is not None:
            surface = np.asarray(surface_m, dtype=np.float64)
            surface_res = float(surface_resolution_m if surface_resolution_m is not None else math.nan)
            if surface.ndim != 2 or surface.shape[1] != 3 or not np.all(np.isfinite(surface)):
                raise ValueError(f"surface_m must be a finite (N, 3) array, got shape {surface.shape}")
            ratio = resolution_m / surface_res
            if not (math.isfinite(ratio) and ratio >= 1 and abs(ratio - round(ratio)) < 1e-6):
                raise ValueError(f"surface_resolution_m must divide resolution_m {resolution_m}, got {surface_resolution_m}")
            # Only points inside seen voxels: the voxels' distance field must bound the cells.
            # (A point on a voxel face belongs to either voxel: float keys may disagree with the map's.)
            seen_keys = _packed_keys(seen, resolution_m)
            surface = surface[np.isin(_packed_keys(surface - 1e-9, resolution_m), seen_keys)
                              | np.isin(_packed_keys(surface + 1e-9, resolution_m), seen_keys)]
            surface = np.vstack([surface, _faces_of_voxels_without_points(seen, resolution_m, surface, surface_res)])
        self._surface_octree = octree_of_centers(seen if surface is None else surface, surface_res)
        self._map_clearance_m = float(clearance_m)
        if self._broad_phase is not None:
            self._broad_phase.set_occupied_voxels(seen, resolution_m, clearance_m, surface_m=surface,
                                                  surface_cell_m=None if surface is None else
                                                  _sphere_cell_m(surface_res, resolution_m), tiers=TIERS)

    @contextlib.contextmanager
    def anchored(self: CollisionWorld, states: npt.ArrayLike, radius_rad: float) -> Iterator[None]:
        """Within the block, states within `radius_rad` of one of `states` (K, dof) get the near-surface
        allowance (see the module docstring). Nests: the inner block's anchors hold inside it."""
        anchors = np.asarray(states, dtype=np.float64).reshape(-1, self._robot.dof)
        if not radius_rad >= 0:  # NaN fails too; inf releases the clearance everywhere
            raise ValueError(f"radius_rad must be >= 0, got {radius_rad}")
        saved = self._anchors, self._anchor_radius_sq
        self._anchors, self._anchor_radius_sq = anchors, float(radius_rad) ** 2
        try:
            yield
        finally:
            self._anchors, self._anchor_radius_sq = saved

    @property
    def anchors(self) -> FloatArray:
        """(K, dof) anchors of the innermost `anchored` block; (0, dof) outside one."""
        return self._anchors

    def clearance_tier(self, q: FloatArray) -> int:
        """The clearance tier of `q`: t in [0, TIERS) keeps clearance_m * t / TIERS (0: only off
        the surface); -1, the full clearance (far from every anchor, or no allowance)."""
        if self._surface_octree is None or not self._anchors.shape[0] or self._anchor_radius_sq <= 0:
            return -1
        # A loop of dot products over the few anchors: a third of one vectorised norm and min.
        nearest_sq = math.inf
        for anchor in self._anchors:
            offset = anchor - q
            nearest_sq = min(nearest_sq, float(offset.dot(offset)))
        return _tier(nearest_sq, self._anchor_radius_sq)

    def _map_aware_check(self: CollisionWorld, q: FloatArray, *, first_only: bool, padded: bool = True) -> list[tuple[str, str]]:
        """`_check` after the broad phase, with the map's near-anchor allowance where it holds."""
        tier = self.clearance_tier(q)
        # The spheres contain the padded hulls: when they touch nothing, neither does FCL.
        if self._broad_phase_usable() and not self._broad_phase.state_suspect(q, tier=tier):
            return []
        return self._check(q, first_only=first_only, padded=padded, tier=tier)

    @property
    def tier_anchors(self) -> tuple[FloatArray | None, float]:
        """The anchors (K, dof) and squared radius the clearance tiers are measured by; None
        where `clearance_tier` is -1 for every state."""
        if self._surface_octree is None or not self._anchors.shape[0] or self._anchor_radius_sq <= 0:
            return None, 0.0
        return self._anchors, self._anchor_radius_sq

    def touches_cubes(self: CollisionWorld, q: FloatArray, centers_m: FloatArray, side_m: float) -> bool:
        """True when a padded link at `q` touches one of the axis-aligned cubes of edge `side_m`
        centered at `centers_m` (N, 3), e.g. voxels. Only the robot, none of the world's objects.

        Cheaper than `set_objects` + `in_collision` for a few voxels checked once: no
        SceneObjects and no broad phase rebuilt, one shared box shape, an AABB test first."""
        centers = self._pose(self._robot.validate_q(q))
        cubes = np.asarray(centers_m, dtype=np.float64).reshape(-1, 3)
        gap = np.maximum(np.abs(centers[:, None, :] - cubes[None]) - 0.5 * side_m, 0.0)
        near = np.einsum("skj,skj->sk", gap, gap) <= self._padded_radii_sq
        cube = fcl.Box(side_m, side_m, side_m)
        for s, k in zip(*np.nonzero(near)):
            if self._collide(self._posed_obj(int(s), padded=True), fcl.CollisionObject(cube, fcl.Transform(cubes[k]))):
                return True
        return False


def _sphere_cell_m(surface_res_m: float, resolution_m: float) -> float:
    """Cells of the spheres' surface grid: multiples of the surface's cells (so they hold them),
    nested in the voxels, at least `MIN_SPHERE_CELL_M` (their grid spans the whole scene)."""
    cells = round(resolution_m / surface_res_m)
    for k in range(max(1, math.ceil(MIN_SPHERE_CELL_M / surface_res_m - 1e-9)), cells + 1):
        if cells % k == 0:
            return k * surface_res_m
    return resolution_m


def clearance_fractions(distance_rad: npt.ArrayLike, radius_rad: float) -> FloatArray:
    """The share of the clearance kept at joint-space distances `distance_rad` from the nearest
    anchor, the tiers of `CollisionWorld.anchored` (1 from `radius_rad` on, 0 within a tier of
    the anchor); all ones when `radius_rad` is 0."""
    distance = np.asarray(distance_rad, dtype=np.float64)
    if radius_rad <= 0:
        return np.ones_like(distance)
    tiers = np.minimum(TIERS - 1, np.floor(TIERS * distance / radius_rad))
    return np.where(distance >= radius_rad, 1.0, tiers / TIERS)


def _tier(distance_sq: float, radius_sq: float) -> int:
    if distance_sq >= radius_sq:
        return -1
    return min(TIERS - 1, int(TIERS * math.sqrt(distance_sq / radius_sq)))


def _faces_of_voxels_without_points(seen_m: FloatArray, resolution_m: float, surface_m: FloatArray,
                                    cell_m: float) -> FloatArray:
    """Centers of the surface cells on the faces of the seen voxels that hold no seen point (K, 3) [m].

    A map holds voxels no point of the surface lies in: support completed under shadows, space
    filled below what was seen, voxels kept by the map's own history. They were judged occupied,
    so the links keep off them too, at their faces: a face shared with another such voxel is
    inside what is occupied and is left out; one against a voxel with points is kept.
    """
    voxels = np.floor(seen_m / resolution_m).astype(np.int64)
    empty = voxels[~np.isin(_packed_keys(seen_m, resolution_m), _packed_keys(surface_m, resolution_m))]
    if not empty.shape[0]:
        return np.zeros((0, 3))
    n = int(round(resolution_m / cell_m))
    empty_keys = _packed_keys((empty + 0.5) * resolution_m, resolution_m)
    grid = np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="ij"), axis=-1).reshape(-1, 2)
    faces = []
    for axis in range(3):
        for side in (0, n - 1):
            step = np.zeros(3, dtype=np.int64)
            step[axis] = 1 if side else -1
            exposed = empty[~np.isin(_packed_keys((empty + step + 0.5) * resolution_m, resolution_m), empty_keys)]
            cells = np.insert(grid, axis, side, axis=1)  # (n*n, 3) cell indices on this face
            faces.append((exposed[:, None, :] * resolution_m + (cells[None] + 0.5) * cell_m).reshape(-1, 3))
    return np.vstack(faces)


def _packed_keys(points_m: FloatArray, resolution_m: float) -> np.ndarray:
    """One int64 per grid cell of side `resolution_m` holding each point (N, 3)."""
    keys = np.floor(np.asarray(points_m, dtype=np.float64).reshape(-1, 3) / resolution_m).astype(np.int64) + (1 << 20)
    return (keys[:, 0] << 42) | (keys[:, 1] << 21) | keys[:, 2]
