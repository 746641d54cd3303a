"""The occupancy grids the sphere broad phase tests against: a map's voxels with a distance
field that culls, the finer cells of its seen surface, and per voxel the box of its cells."""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np
from scipy.ndimage import distance_transform_edt

from robonav.pipeline.types import FloatArray

MAX_GRID_CELLS = 60_000_000
"""Largest grid a layer may span (a bool and a float64 per cell)."""


class VoxelLayer(NamedTuple):
    """Occupied cubes on a grid and, for voxels, a lower bound on the distance to them."""


    field: FloatArray
    """Lower bound on the distance to the occupied cubes at each cell center [m]."""
    origin: FloatArray
    """Center of cell (0, 0, 0) [m]."""
    voxel: float
    box: FloatArray
    """(2, 3) bounding box of the occupied cubes [m]."""
    occupied: np.ndarray


def voxel_layer(keys: np.ndarray, voxel_m: float, margin_cells: int, key0_center_m: FloatArray) -> VoxelLayer:
    """The cubes of grid `keys` (N, 3) (cell k centered at key0_center_m + k * voxel_m) with a Euclidean
    distance field on a grid covering them plus `margin_cells`. A lookup at point p in cell c
    returns edt(c) - |p - center(c)| - half a cube's diagonal, a lower bound on the distance from
    p to any occupied cube; outside the grid the distance to the cubes' bounding box is used."""
    low = keys.min(axis=0) - margin_cells
    index = keys - low
    dims = index.max(axis=0) + margin_cells + 1
    if int(np.prod(dims)) > MAX_GRID_CELLS:
        raise ValueError(f"occupancy spans {dims.tolist()} cells, more than {MAX_GRID_CELLS}")
    occupied = np.zeros(tuple(dims), dtype=bool)
    occupied[index[:, 0], index[:, 1], index[:, 2]] = True
    field = distance_transform_edt(~occupied) * voxel_m - 0.5 * math.sqrt(3.0) * voxel_m
    box = np.array([key0_center_m + (keys.min(axis=0) - 0.5) * voxel_m, key0_center_m + (keys.max(axis=0) + 0.5) * voxel_m])
    return VoxelLayer(np.ascontiguousarray(field, dtype=np.float64), key0_center_m + low * voxel_m, voxel_m, box, occupied)


def cell_layer(keys: np.ndarray, cell_m: float) -> VoxelLayer:
    """Occupied cells of grid `keys` (N, 3) (cell k spans [k, k + 1) * cell_m), without a distance field."""
    low = keys.min(axis=0)
    dims = keys.max(axis=0) - low + 1
    if int(np.prod(dims)) > MAX_GRID_CELLS:
        raise ValueError(f"surface spans {dims.tolist()} cells, more than {MAX_GRID_CELLS}")
    occupied = np.zeros(tuple(dims), dtype=bool)
    occupied[tuple((keys - low).T)] = True
    return VoxelLayer(np.zeros((1, 1, 1)), (low + 0.5) * cell_m, cell_m, np.zeros((2, 3)), occupied)


def cell_boxes(fine: VoxelLayer, coarse: VoxelLayer) -> tuple[np.ndarray, np.ndarray]:
    """Per voxel of `coarse`, the box of the occupied `fine` cells inside it (`kernels.touches_cells`):
    a grid of rows of the (V, 6) boxes (-1: no cell), and the boxes as first and last `fine`
    indices per axis."""
    cells = np.argwhere(fine.occupied)
    centers = fine.origin + cells * fine.voxel
    voxel = np.round((centers - coarse.origin) / coarse.voxel).astype(np.int64)
    dims = np.array(coarse.occupied.shape)
    if np.any(voxel < 0) or np.any(voxel >= dims):
        raise ValueError("surface cells lie outside the voxels' grid")
    flat = np.ravel_multi_index(tuple(voxel.T), tuple(dims))
    voxels, row = np.unique(flat, return_inverse=True)
    boxes = np.empty((voxels.shape[0], 6), dtype=np.int64)
    boxes[:, :3] = np.iinfo(np.int64).max
    boxes[:, 3:] = -1
    np.minimum.at(boxes[:, :3], row, cells)
    np.maximum.at(boxes[:, 3:], row, cells)
    slot = np.full(coarse.occupied.size, -1, dtype=np.int32)
    slot[voxels] = np.arange(voxels.shape[0])
    return slot.reshape(coarse.occupied.shape), boxes


def column_ranges(held: np.ndarray) -> np.ndarray:
    """(I, J, 2) int64: per column of the grid `held` (I, J, K) bool, the first and last k that
    holds something, or (K, -1) when none does (`kernels.touches_cells` skips what lies outside)."""
    depth = held.shape[2]
    any_held = held.any(axis=2)
    first = np.where(any_held, held.argmax(axis=2), depth)
    last = np.where(any_held, depth - 1 - held[..., ::-1].argmax(axis=2), -1)
    return np.ascontiguousarray(np.stack([first, last], axis=-1), dtype=np.int64)


def field_to_cell_boxes(coarse: VoxelLayer, fine: VoxelLayer, slot: np.ndarray, boxes: np.ndarray,
                        reach_m: float) -> VoxelLayer:
    """`coarse` with its distance field raised, up to `reach_m`, to the exact distance from each
    cell center to the nearest box of `fine` cells (`cell_boxes`): still a lower bound on the
    distance to the cells, which lie in the boxes.

    The voxels' field bounds the distance to whole cubes from a cell's center less half a
    cube's diagonal; a seen surface crosses a cube as a slab, about a centimetre inside that
    bound. A sphere the loose bound sends to the cell test (`kernels.touches_cells`) mostly
    touches nothing, and that test is most of an edge's cost on a map: on the edges of an MBM
    `box` cloud plan, 18 cell tests an edge (2.5 touching) became 9, and an edge 39 -> 32 us.
    Building it costs about 40 ms for a map of 19,000 voxels with cells."""
    voxels = np.argwhere(slot >= 0)
    rows = slot[voxels[:, 0], voxels[:, 1], voxels[:, 2]]
    lows = fine.origin + (boxes[rows, :3] - 0.5) * fine.voxel
    highs = fine.origin + (boxes[rows, 3:] + 0.5) * fine.voxel
    nearest_sq = _box_distances_sq(coarse.field.shape, coarse.origin, coarse.voxel, lows, highs, float(reach_m))
    return coarse._replace(field=np.maximum(coarse.field, np.sqrt(nearest_sq)))


@nb.njit(cache=True)
def _box_distances_sq(shape: tuple[int, int, int], origin: FloatArray, voxel: float, lows: FloatArray, highs: FloatArray,
                      reach: float) -> FloatArray:  # pragma: no cover (compiled)
    """Per cell center of a grid of `shape`, the squared distance to the nearest box [lows, highs]
    (B, 3), at most reach**2: each box writes the cells within `reach` of it."""
    nearest = np.full(shape, reach * reach)
    for b in range(lows.shape[0]):
        i0 = max(int(math.ceil((lows[b, 0] - reach - origin[0]) / voxel)), 0)
        i1 = min(int(math.floor((highs[b, 0] + reach - origin[0]) / voxel)), shape[0] - 1)
        j0 = max(int(math.ceil((lows[b, 1] - reach - origin[1]) / voxel)), 0)
        j1 = min(int(math.floor((highs[b, 1] + reach - origin[1]) / voxel)), shape[1] - 1)
        k0 = max(int(math.ceil((lows[b, 2] - reach - origin[2]) / voxel)), 0)
        k1 = min(int(math.floor((highs[b, 2] + reach - origin[2]) / voxel)), shape[2] - 1)
        for i in range(i0, i1 + 1):
            x = origin[0] + i * voxel
            dx = max(lows[b, 0] - x, 0.0, x - highs[b, 0])
            for j in range(j0, j1 + 1):
                y = origin[1] + j * voxel
                dy = max(lows[b, 1] - y, 0.0, y - highs[b, 1])
                dxy = dx * dx + dy * dy
                if dxy >= reach * reach:
                    continue
                for k in range(k0, k1 + 1):
                    z = origin[2] + k * voxel
                    dz = max(lows[b, 2] - z, 0.0, z - highs[b, 2])
                    nearest[i, j, k] = min(nearest[i, j, k], dxy + dz * dz)
    return nearest


NO_SLOTS = np.full((1, 1, 1), -1, dtype=np.int32)
NO_BOXES = np.zeros((0, 6), dtype=np.int64)
