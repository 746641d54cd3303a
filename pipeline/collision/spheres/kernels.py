"""Compiled kernels of the sphere broad phase (`broad_phase.SphereBroadPhase` packs their arguments).

Point-to-primitive and point-to-voxel distances for one point; the checks that use them, several
states at a time, are in `broad_phase_lanes`. The small helpers are inlined into the loops
(`inline="always"`): a call per sphere would cost more than the arithmetic it does.
"""

from __future__ import annotations

import math

import numba as nb

from robonav.pipeline.collision.spheres.grid_layers import NO_BOXES, NO_SLOTS
from robonav.pipeline.types import BoolArray, FloatArray, IntArray

BOX, SPHERE, CYLINDER, CAPSULE = 0, 1, 2, 3
CONTACT_EPS_M = 1e-9
"""Touching counts as contact (FCL reports touching shapes as colliding)."""


@nb.njit(cache=True, inline="always")
def _primitive_distance(px: float, py: float, pz: float, kind: int, p0: float, p1: float, p2: float) -> float:
    """Signed distance from a point in the object's frame to a box/sphere/cylinder/capsule [m]."""
    if kind == BOX:
        qx, qy, qz = abs(px) - p0, abs(py) - p1, abs(pz) - p2
        ox, oy, oz = max(qx, 0.0), max(qy, 0.0), max(qz, 0.0)
        return math.sqrt(ox * ox + oy * oy + oz * oz) + min(max(qx, max(qy, qz)), 0.0)
    if kind == SPHERE:
        return math.sqrt(px * px + py * py + pz * pz) - p0
    if kind == CYLINDER:
        radial = math.sqrt(px * px + py * py) - p0
        axial = abs(pz) - p1
        orad, oax = max(radial, 0.0), max(axial, 0.0)
        return math.sqrt(orad * orad + oax * oax) + min(max(radial, axial), 0.0)
    z = min(max(pz, -p1), p1)
    dz = pz - z
    return math.sqrt(px * px + py * py + dz * dz) - p0


@nb.njit(cache=True, inline="always")
def object_distance(x: float, y: float, z: float, k: int, kind: IntArray, rotation: FloatArray, translation: FloatArray,
                    param: FloatArray) -> float:
    dx, dy, dz = x - translation[k, 0], y - translation[k, 1], z - translation[k, 2]
    px = rotation[k, 0, 0] * dx + rotation[k, 1, 0] * dy + rotation[k, 2, 0] * dz
    py = rotation[k, 0, 1] * dx + rotation[k, 1, 1] * dy + rotation[k, 2, 1] * dz
    pz = rotation[k, 0, 2] * dx + rotation[k, 1, 2] * dy + rotation[k, 2, 2] * dz
    return _primitive_distance(px, py, pz, kind[k], param[k, 0], param[k, 1], param[k, 2])


@nb.njit(cache=True, inline="always")
def voxel_distance(x: float, y: float, z: float, grid: FloatArray, origin: FloatArray, voxel: float, box: FloatArray) -> float:
    """Lower bound on the distance from a point to the occupied cubes [m]."""
    fx, fy, fz = (x - origin[0]) / voxel, (y - origin[1]) / voxel, (z - origin[2]) / voxel
    i, j, k = int(math.floor(fx + 0.5)), int(math.floor(fy + 0.5)), int(math.floor(fz + 0.5))
    if 0 <= i < grid.shape[0] and 0 <= j < grid.shape[1] and 0 <= k < grid.shape[2]:
        ex, ey, ez = (fx - i) * voxel, (fy - j) * voxel, (fz - k) * voxel
        return grid[i, j, k] - math.sqrt(ex * ex + ey * ey + ez * ez)
    ox = max(box[0, 0] - x, 0.0, x - box[1, 0])
    oy = max(box[0, 1] - y, 0.0, y - box[1, 1])
    oz = max(box[0, 2] - z, 0.0, z - box[1, 2])
    return math.sqrt(ox * ox + oy * oy + oz * oz)


@nb.njit(cache=True)
def touches_cells(x: float, y: float, z: float, radius: float, occupied: BoolArray, origin: FloatArray, voxel: float,
                  fine: BoolArray, fine_origin: FloatArray, fine_voxel: float, fine_slot: IntArray,
                  fine_box: IntArray, column: IntArray) -> bool:
    """Whether the sphere touches an occupied cell of `fine`, a grid nested in the voxels'
    (`occupied`, cell side `voxel`) whose occupied cells lie in occupied voxels: the voxels
    the sphere's ball reaches first, then the box of their cells, then only the cells in that
    box. With `fine_voxel == voxel` the cells are the voxels (`touches_voxels`).

    `fine_slot` (the voxels' grid): -1 for a voxel without cells, else a row of `fine_box`
    (V, 6): the smallest box of `fine` indices (first i, j, k, then last i, j, k) holding the
    voxel's cells. A seen surface crosses a voxel as a slab a cell or two thick: a sphere near
    the voxel but off the slab is settled by one box distance instead of a loop over its cells
    (a map's surface test ran at 2.5 times the cost of the voxels' before). `column` (I, J, 2):
    per column of the voxels' grid the first and last k of a voxel with cells
    (`grid_layers.column_ranges`), or of an occupied voxel when the cells are the voxels."""
    cells = fine_voxel != voxel
    half = 0.5 * voxel
    lo_i, hi_i = _ball_cells(x, radius, origin[0], voxel, occupied.shape[0])
    lo_j, hi_j = _ball_cells(y, radius, origin[1], voxel, occupied.shape[1])
    lo_k, hi_k = _ball_cells(z, radius, origin[2], voxel, occupied.shape[2])
    r2 = radius * radius
    for i in range(lo_i, hi_i + 1):
        for j in range(lo_j, hi_j + 1):
            first_k, last_k, dxy = _column_reach(x, y, z, r2, origin, voxel, i, j, lo_k, hi_k, column)
            for k in range(first_k, last_k + 1):
                if not (occupied[i, j, k] if not cells else fine_slot[i, j, k] >= 0):
                    continue
                dz = max(abs(z - (origin[2] + k * voxel)) - half, 0.0)
                if dxy + dz * dz > r2:
                    continue
                if not cells:  # the cells are the voxels: this one is within reach
                    return True
                slot = fine_slot[i, j, k]
                # The box of the voxel's cells, then its cells that the sphere's box overlaps.
                x0 = fine_origin[0] + (fine_box[slot, 0] - 0.5) * fine_voxel
                x1 = fine_origin[0] + (fine_box[slot, 3] + 0.5) * fine_voxel
                y0 = fine_origin[1] + (fine_box[slot, 1] - 0.5) * fine_voxel
                y1 = fine_origin[1] + (fine_box[slot, 4] + 0.5) * fine_voxel
                z0 = fine_origin[2] + (fine_box[slot, 2] - 0.5) * fine_voxel
                z1 = fine_origin[2] + (fine_box[slot, 5] + 0.5) * fine_voxel
                ex, ey, ez = max(x0 - x, 0.0, x - x1), max(y0 - y, 0.0, y - y1), max(z0 - z, 0.0, z - z1)
                if ex * ex + ey * ey + ez * ez > r2:
                    continue
                if _touches_cells_in(x, y, z, r2, max(x0, x - radius), min(x1, x + radius), max(y0, y - radius),
                                     min(y1, y + radius), max(z0, z - radius), min(z1, z + radius), fine, fine_origin,
                                     fine_voxel):
                    return True
    return False


@nb.njit(cache=True, inline="always")
def _ball_cells(center: float, radius: float, origin: float, voxel: float, size: int) -> tuple[int, int]:
    """First and last index along one axis of the cells (side `voxel`, cell 0 centered at
    `origin`) that a ball reaches, clipped to [0, size)."""
    return (max(int(math.ceil((center - radius - origin) / voxel - 0.5)), 0),
            min(int(math.floor((center + radius - origin) / voxel + 0.5)), size - 1))


@nb.njit(cache=True, inline="always")
def _column_reach(x: float, y: float, z: float, r2: float, origin: FloatArray, voxel: float, i: int, j: int, lo_k: int,
                  hi_k: int, column: IntArray) -> tuple[int, int, float]:
    """The k range of column (i, j) whose cubes a ball of squared radius r2 at (x, y, z) may
    reach, cut to the column's occupied range (empty: first > last), and the squared distance
    from the ball's center to the column in the xy plane.

    Most columns a ball near a surface spans hold no occupied voxel, or only far above or below
    it: their range settles them before any voxel is read (a sphere beside a 2 cm map's surface
    read about 90 voxels, not 285, and was tested in half the time)."""
    first_occupied, last_occupied = column[i, j, 0], column[i, j, 1]
    if first_occupied > hi_k or last_occupied < lo_k:
        return 0, -1, 0.0
    dx = max(abs(x - (origin[0] + i * voxel)) - 0.5 * voxel, 0.0)
    dy = max(abs(y - (origin[1] + j * voxel)) - 0.5 * voxel, 0.0)
    dxy = dx * dx + dy * dy
    if dxy > r2:
        return 0, -1, dxy
    reach_z = math.sqrt(r2 - dxy)
    first_k = max(int(math.ceil((z - reach_z - origin[2]) / voxel - 0.5)), lo_k, first_occupied)
    last_k = min(int(math.floor((z + reach_z - origin[2]) / voxel + 0.5)), hi_k, last_occupied)
    return first_k, last_k, dxy


@nb.njit(cache=True, inline="always")
def _touches_cells_in(x: float, y: float, z: float, r2: float, x0: float, x1: float, y0: float, y1: float, z0: float,
                      z1: float, fine: BoolArray, origin: FloatArray, cell: float) -> bool:
    """Whether an occupied cell of `fine` overlapping the box [x0, x1] x [y0, y1] x [z0, z1] (inside
    one voxel) is within sqrt(r2) of (x, y, z)."""
    half = 0.5 * cell
    lo_i = max(int(math.ceil((x0 - origin[0]) / cell - 0.5)), 0)
    hi_i = min(int(math.floor((x1 - origin[0]) / cell + 0.5)), fine.shape[0] - 1)
    lo_j = max(int(math.ceil((y0 - origin[1]) / cell - 0.5)), 0)
    hi_j = min(int(math.floor((y1 - origin[1]) / cell + 0.5)), fine.shape[1] - 1)
    lo_k = max(int(math.ceil((z0 - origin[2]) / cell - 0.5)), 0)
    hi_k = min(int(math.floor((z1 - origin[2]) / cell + 0.5)), fine.shape[2] - 1)
    for i in range(lo_i, hi_i + 1):
        dx = max(abs(x - (origin[0] + i * cell)) - half, 0.0)
        for j in range(lo_j, hi_j + 1):
            dy = max(abs(y - (origin[1] + j * cell)) - half, 0.0)
            dxy = dx * dx + dy * dy
            if dxy > r2:
                continue
            for k in range(lo_k, hi_k + 1):
                if fine[i, j, k]:
                    dz = max(abs(z - (origin[2] + k * cell)) - half, 0.0)
                    if dxy + dz * dz <= r2:
                        return True
    return False


@nb.njit(cache=True, inline="always")
def touches_voxels(x: float, y: float, z: float, radius: float, occupied: BoolArray, origin: FloatArray,
                   voxel: float, column: IntArray) -> bool:
    """Whether the sphere touches an occupied cube: exact point-to-cube distances over the cubes
    its ball reaches, in the columns' occupied ranges (`column`, see `touches_cells`).

    The distance field alone is a lower bound loose by up to 1.7 voxels (the offset from the
    cell center plus half the cube's diagonal); this second step, taken only where the field
    says a sphere may touch, keeps spheres from flagging states FCL clears: of 1085 random
    Panda states beside a slab of 2 cm voxels (self-collision aside), 39 were flagged but
    free with the field alone, 21 with this step."""
    return touches_cells(x, y, z, radius, occupied, origin, voxel, occupied, origin, voxel, NO_SLOTS, NO_BOXES, column)
