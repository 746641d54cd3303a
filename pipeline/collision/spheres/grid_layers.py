"""The occupancy grids the sphere broad phase tests against: a map's voxels with a distance
field that culls, the finer cells of its seen surface, and per voxel the box of its cells."""

from __future__ import annotations

import math
from typing import NamedTuple

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


NO_SLOTS = np.full((1, 1, 1), -1, dtype=np.int32)
NO_BOXES = np.zeros((0, 6), dtype=np.int64)
